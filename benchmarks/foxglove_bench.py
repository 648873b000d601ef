#!/usr/bin/env python3
"""Watching the S1 rig in Foxglove while it records: what the viewer costs the container, and what it costs
when the bridge is a process of its own over DDS.

Every mode runs the S1 rig of examples/sensors.yaml (two 1920x1080 rgb8 cameras at 30 Hz, a LiDAR, an IMU)
with a recorder in the same container (intra-process, all rig topics; the bag split every GiB, the last 2
files kept, so a run needs little disk), and Foxglove's own client (tests/foxglove_client, node) as the viewer:

* ``no_viewer``: the rig recording, no bridge;
* ``in_container``: ``components::FoxgloveBridge`` loaded into the container (intra-process), one client
  watching both cameras at full rate;
* ``out_of_process``: the same component in a second container process without intra-process comms (a Python
  bridge over DDS, the same SDK), one client watching both cameras;
* ``stalled``: as ``in_container`` with a second client that stops reading (SIGSTOP) for the whole window;
* ``video``: as ``in_container``, the client watching both cameras' video channels (``<image>/video``: H.264 at
  the bridge's defaults, 640 px wide at 10 Hz) instead of the raw frames.

Measured over each window (the same length in every mode): CPU seconds per second of the rig's container (and
of the bridge's process and the viewers), the recorder's drops and their reasons, the frames each client
decoded and the gaps in their sequence numbers, and for a stalled client what the bridge handed to its outbox
against what it got; for video, the messages received and the encoder's counts.

    python benchmarks/foxglove_bench.py [--seconds 30] [--modes ...] [--quick]

Results: benchmarks/results/<date>-<commit>/foxglove.json.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import isolation  # noqa: F401  (first: the ROS environment before rclpy is imported)
import yaml

REPO = Path(__file__).resolve().parents[1]

import rclpy  # noqa: E402
from rclpy.node import Node  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from benchmarks.fleet_bench import cpu_seconds  # noqa: E402
from benchmarks.result_folder import add_run_arguments, run_header, save, work_directory  # noqa: E402
from ipc_testing import ContainerProcess, call, wait_until  # noqa: E402
from ipc_testing.foxglove_client import FoxgloveClient, bridge_url, gaps, install_client  # noqa: E402

MODES = ("no_viewer", "in_container", "out_of_process", "stalled", "video")
CAMERAS = ["/front_camera/image_raw", "/rear_camera/image_raw"]
VIDEOS = [f"{camera}/video" for camera in CAMERAS]
RIG = REPO / "examples" / "sensors.yaml"


def load_file(workdir: Path, mode: str) -> Path:
    """The S1 rig, a recorder of its topics and (in_container, stalled) the bridge, all intra-process."""
    components = yaml.safe_load(RIG.read_text())["components"]
    topics = [*CAMERAS, "/front_camera/camera_info", "/rear_camera/camera_info", "/lidar/points", "/imu/imu"]
    components.append({"package": "components", "plugin": "components::Recorder", "name": "recorder",
                       "parameters": {"record.topics": topics, "storage.uri": str(workdir / "bag"),
                                      "storage.max_bagfile_size": 1 << 30, "storage.max_bag_files": 2},
                       "extra_arguments": {"use_intra_process_comms": True}})
    if mode in ("in_container", "stalled", "video"):
        components.append(bridge_component(True))
    path = workdir / f"{mode}.yaml"
    path.write_text(yaml.safe_dump({"components": components}))
    return path


def bridge_component(intra_process: bool) -> dict[str, Any]:
    return {"package": "components", "plugin": "components::FoxgloveBridge", "name": "foxglove_bridge",
            "parameters": {"port": 0, "topic_whitelist": [*CAMERAS, *VIDEOS]},
            "extra_arguments": {"use_intra_process_comms": intra_process}}


def trigger_json(node: Node, service: str) -> dict[str, Any]:
    client = node.create_client(Trigger, service)
    try:
        return json.loads(call(node, client, Trigger.Request(), timeout=30.0, again=True).message)
    finally:
        node.destroy_client(client)


def recorder_topics(node: Node) -> dict[str, dict[str, int]]:
    return trigger_json(node, "/recorder/get_stats")["current"]["topics"]


def recorder_drop_reasons(node: Node) -> dict[str, dict[str, int]]:
    """Drops per topic and reason since the recording began (warm-up included)."""
    return trigger_json(node, "/recorder/get_stats")["current"]["drop_reasons"]


class Rig:
    """The container of one mode, the bridge's process (out_of_process) and the viewers."""

    def __init__(self, mode: str, workdir: Path) -> None:
        self.mode = mode
        self.container = ContainerProcess("--load", str(load_file(workdir, mode)), name="rig", cwd=REPO,
                                          log_path=workdir / f"{mode}.log")
        self.bridge: ContainerProcess | None = None
        if mode == "out_of_process":
            path = workdir / "bridge.yaml"
            path.write_text(yaml.safe_dump({"components": [bridge_component(False)]}))
            self.bridge = ContainerProcess("--load", str(path), name="bridge_process", cwd=REPO,
                                           log_path=workdir / "bridge.log")
        self.viewers: list[FoxgloveClient] = []

    def open_viewers(self) -> None:
        if self.mode == "no_viewer":
            return
        served = self.bridge or self.container
        if not wait_until(lambda: "Foxglove bridge listening" in served.output, 60.0):
            raise RuntimeError(f"no bridge came up:\n{served.output[-3000:]}")
        url = bridge_url(served.output)
        for _ in range(2 if self.mode == "stalled" else 1):
            viewer = FoxgloveClient(url)
            viewer.subscribe(*self.topics)
            self.viewers.append(viewer)
        for viewer in self.viewers:
            for topic in self.topics:
                if not wait_until(lambda: messages(viewer, topic) >= 10, 60.0):
                    raise RuntimeError(f"the viewer got no messages of {topic}: {viewer.events[-3:]}")

    @property
    def topics(self) -> list[str]:
        """The channels the viewers watch."""
        return VIDEOS if self.mode == "video" else CAMERAS

    def pids(self) -> dict[str, int]:
        pids = {"container": self.container.pid}
        if self.bridge is not None:
            pids["bridge_process"] = self.bridge.pid
        pids.update({f"viewer_{n}": v.process.pid for n, v in enumerate(self.viewers)})
        return pids

    def close(self) -> None:
        for viewer in self.viewers:
            viewer.close()
        for process in (self.bridge, self.container):
            if process is not None:
                with process:
                    if process.alive():
                        process.stop(timeout=60.0, check=False)


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def run_mode(mode: str, node: Node, seconds: float, workdir: Path) -> dict[str, Any]:
    rig = Rig(mode, workdir)
    try:
        if not wait_until(lambda: all(recorder_topics(node).get(t, {}).get("received") for t in CAMERAS), 90.0):
            raise RuntimeError(f"the recorder received nothing:\n{rig.container.output[-3000:]}")
        rig.open_viewers()
        if mode == "stalled":
            rig.viewers[1].pause()
        pids = rig.pids()
        frames_before = [{t: messages(v, t) for t in rig.topics} for v in rig.viewers]
        before, recorder_before, rss_before = ({k: cpu_seconds(p) for k, p in pids.items()}, recorder_topics(node),
                                               rss_mb(rig.container.pid))
        started = time.monotonic()
        time.sleep(seconds)
        after, elapsed = {k: cpu_seconds(p) for k, p in pids.items()}, time.monotonic() - started
        recorder_after, rss_after = recorder_topics(node), rss_mb(rig.container.pid)
        frames_after = [{t: messages(v, t) for t in rig.topics} for v in rig.viewers]
        result: dict[str, Any] = {
            "cpu_per_s": {k: (after[k] - before[k]) / elapsed for k in pids},
            "container_rss_mb": [rss_before, rss_after],
            "recorder": {t: {k: recorder_after[t][k] - recorder_before.get(t, {}).get(k, 0)
                             for k in ("received", "written", "dropped", "queue_dropped")} for t in recorder_after},
            "recorder_drop_reasons": recorder_drop_reasons(node),
            "viewers": [viewer_figures(v, a, b, elapsed) for v, a, b in zip(rig.viewers, frames_before, frames_after)]}
        if mode != "no_viewer":
            channels = trigger_json(node, "/foxglove_bridge/get_stats")["channels"]
            figures = ("received", "sent", "sent_bytes", "dropped", "throttled", "encoder")
            result["bridge"] = {t: {k: channels[t][k] for k in figures if k in channels[t]} for t in rig.topics}
        if mode == "stalled":
            result["stalled"] = stalled_figures(rig, node)
        return result
    finally:
        rig.close()


def messages(viewer: FoxgloveClient, topic: str) -> int:
    return len(viewer.of("message", lambda e: e["topic"] == topic))


def viewer_figures(viewer: FoxgloveClient, before: dict[str, int], after: dict[str, int],
                   elapsed: float) -> dict[str, Any]:
    """Messages a second per channel; gaps in the drivers' sequence numbers (raw frames; video has none)."""
    return {topic: {"fps": (after[topic] - before[topic]) / elapsed,
                    "gaps": gaps(viewer.sequences(topic)[before[topic]:after[topic]]) if topic in CAMERAS else 0}
            for topic in before}


def stalled_figures(rig: Rig, node: Node) -> dict[str, Any]:
    """Resume the stalled viewer, let it catch up; what the bridge handed to its outbox and what it got."""
    stalled, watcher = rig.viewers[1], rig.viewers[0]
    stalled.resume()
    last = watcher.sequences(CAMERAS[0])[-1]
    wait_until(lambda: (s := stalled.sequences(CAMERAS[0])) and s[-1] >= last, 30.0)
    channels = trigger_json(node, "/foxglove_bridge/get_stats")["channels"]
    figures = {}
    for topic in CAMERAS:
        handed = channels[topic]["sent_to"]
        stalled_id = max(handed, key=int)  # the client that connected last
        received = len(stalled.sequences(topic))
        figures[topic] = {"handed_to_outbox": handed[stalled_id], "received": received,
                          "lost_in_outbox": handed[stalled_id] - received, "bridge_dropped": channels[topic]["dropped"]}
    return figures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="window of every mode (and the stall)")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    add_run_arguments(parser, quick="5 s windows")
    args = parser.parse_args()
    if args.quick:
        args.seconds = 5.0
    install_client()
    report: dict[str, Any] = {**run_header("foxglove_bench.py", sys.argv[1:]), "rig": "S1: examples/sensors.yaml",
                              "seconds": args.seconds,
                              "load_before": os.getloadavg()[0]}
    rclpy.init()
    node = Node("foxglove_bench")
    started = time.monotonic()
    try:
        for mode in args.modes:
            print(f"{mode} ...", flush=True)
            with work_directory(args, "foxglove_bench_") as workdir:
                report[mode] = run_mode(mode, node, args.seconds, Path(workdir))
            print(f"  {json.dumps(report[mode])}", flush=True)
    finally:
        node.destroy_node()
        rclpy.shutdown()
    report["elapsed_s"] = time.monotonic() - started
    report["load_after"] = os.getloadavg()[0]
    if args.results:
        print(f"results: {save(report, 'foxglove', Path(args.results))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
