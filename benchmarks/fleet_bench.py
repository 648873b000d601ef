#!/usr/bin/env python3
"""Fleet recording against one recorder over DDS: N computers (network namespaces) with 2 cameras each.

Both modes run the same rig: N hosts as network namespaces on a private bridge (ipc_testing.netns), each with a
container of 2 camera drivers, plus one more host, ``central``, with an empty container.

* ``fleet``: ``ipc-component record start`` loads a local-only recorder into every host's container (zero-copy;
  nothing crosses the network);
* ``central``: the same command records every camera in the central container only (``--no-local-only``), so
  every frame crosses the bridge over DDS (UDP), as a single recorder of a multi-computer robot would.

Measured side by side in one run: the CPU time of every container during the recording window (CPU seconds per
second), the frames recorded and lost (sequence gaps), and per host the cut distance of the start and stop: how
long after the scheduled start the first frame was received, how long before the stop the last.

    python benchmarks/fleet_bench.py [--hosts 2] [--seconds 10] [--width 640 --height 480 --fps 30] [--quick]

Needs root (network namespaces). Results: benchmarks/results/<date>-<commit>/fleet.json.
"""
from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from sensor_msgs.msg import Image  # noqa: E402

from baglib.format import fleet_keys  # noqa: E402
from baglib.format.cdr_read import deserialize  # noqa: E402
from baglib.read.reader import BagReader  # noqa: E402
from benchmarks.result_folder import add_run_arguments, run_header, save, work_directory  # noqa: E402
from ipc_testing import ContainerProcess  # noqa: E402
from ipc_testing.netns import Network, unavailable  # noqa: E402

CENTRAL = "central"
TICK = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


class Rig:
    """The hosts' containers and the central one, on one network."""

    def __init__(self, network: Network, workdir: Path, hosts: list[str], args: argparse.Namespace) -> None:
        self.network, self.workdir = network, workdir
        self.env = network.environment(random.randint(150, 230))
        camera = {"width": args.width, "height": args.height, "fps": args.fps}
        self.containers: dict[str, ContainerProcess] = {}
        for host in [*hosts, CENTRAL]:
            (workdir / host).mkdir()
            components = [] if host == CENTRAL else [
                {"package": "components", "plugin": "components::CameraDriver", "name": f"{host}_cam{i}",
                 "parameters": camera, "extra_arguments": {"use_intra_process_comms": True}} for i in range(2)]
            load = workdir / f"{host}.yaml"
            load.write_text(yaml.safe_dump({"components": components}))
            self.containers[host] = ContainerProcess(
                "--use-intra-process-comms", "--bag-root", str(workdir / host), "--load", str(load),
                name=f"/{host}/container", cwd=REPO, env=self.env, prefix=network.prefix(host),
                log_path=workdir / f"{host}.log")

    def cli(self, *args: str) -> subprocess.CompletedProcess:
        result = subprocess.run([*self.network.prefix("operator"), sys.executable, "-m", "ipc_component.cli", *args],
                                env=dict(os.environ, **self.env), cwd=REPO, capture_output=True, text=True,
                                timeout=120)
        if result.returncode != 0:
            raise RuntimeError(f"ipc-component {' '.join(args)}: {result.stdout}{result.stderr}")
        return result

    def wait_listed(self, deadline: float) -> None:
        while not all(f"/{host}/container" in self.cli("list", "--containers-only").stdout for host in self.containers):
            if time.monotonic() > deadline:
                raise RuntimeError("containers not discovered")

    def cpu(self) -> dict[str, float]:
        return {host: cpu_seconds(process.pid) for host, process in self.containers.items()}

    def stop(self) -> None:
        for process in self.containers.values():
            process.stop()


def run_mode(mode: str, hosts: list[str], args: argparse.Namespace) -> dict[str, Any]:
    with work_directory(args, "fleet_bench_") as workdir, Network([*hosts, CENTRAL]) as network:
        rig = Rig(network, Path(workdir), hosts, args)
        try:
            rig.wait_listed(time.monotonic() + 60)
            targets = [f"/{h}/container" for h in hosts] if mode == "fleet" else [f"/{CENTRAL}/container"]
            extra = [] if mode == "fleet" else ["--no-local-only", "-p", "record.regex:=image_raw$"]
            rig.cli("record", "start", *targets, "--session", mode, "--in", "2", *extra)
            time.sleep(3)  # the window begins 2 s after the command; measure from 1 s into it
            before, started = rig.cpu(), time.monotonic()
            time.sleep(args.seconds)
            after, elapsed = rig.cpu(), time.monotonic() - started
            stopped = rig.cli("record", "stop", "--session", mode).stdout
        finally:
            rig.stop()
        bags = sorted(Path(workdir).glob(f"*/{mode}/*/metadata.yaml"))
        return {"cpu_per_s": {host: (after[host] - before[host]) / elapsed for host in after},
                "cpu_total_per_s": sum(after[h] - before[h] for h in after) / elapsed,
                "bags": [bag_figures(path.parent) for path in bags], "stop_output": stopped}


def bag_figures(bag: Path) -> dict[str, Any]:
    """Frames, gaps and cut distances of one bag (its window from its custom_data)."""
    custom = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["custom_data"]
    start = int(custom[fleet_keys.START_NS]) + int(custom[fleet_keys.CLOCK_OFFSET_NS])
    stop = int(custom[fleet_keys.STOP_NS]) + int(custom[fleet_keys.STOP_CLOCK_OFFSET_NS])
    per_topic: dict[str, list[tuple[int, int]]] = {}
    with BagReader(bag) as reader:
        for message in reader.messages():
            if message.connection.topic.endswith("image_raw"):
                image = deserialize(message.data, Image)
                per_topic.setdefault(message.connection.topic, []).append(
                    (message.log_time_ns, int.from_bytes(bytes(image.data[:8]), "little")))
    topics = {}
    for topic, frames in per_topic.items():
        seqs = sorted(seq for _t, seq in frames)
        topics[topic] = {"frames": len(frames), "gaps": seqs[-1] - seqs[0] + 1 - len(seqs),
                         "start_cut_ms": (frames[0][0] - start) / 1e6, "stop_cut_ms": (stop - frames[-1][0]) / 1e6}
    return {"host": custom[fleet_keys.HOST], "bag": str(bag.name), "topics": topics,
            "clock_offset_ms": int(custom[fleet_keys.CLOCK_OFFSET_NS]) / 1e6}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hosts", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--fps", type=float, default=30.0)
    add_run_arguments(parser, quick="3 s windows")
    args = parser.parse_args()
    if args.quick:
        args.seconds = 3.0
    reason = unavailable()
    if reason:
        print(f"fleet benchmark not run: {reason}")
        return 1
    hosts = [f"h{i + 1}" for i in range(args.hosts)]
    report: dict[str, Any] = {**run_header("fleet_bench.py", sys.argv[1:]), "hosts": args.hosts,
                              "cameras_per_host": 2, "camera": f"{args.width}x{args.height}@{args.fps:g}",
                              "mb_per_s_per_camera": args.width * args.height * 3 * args.fps / 1e6,
                              "seconds": args.seconds, "load_before": os.getloadavg()[0]}
    for mode in ("fleet", "central"):
        print(f"{mode} ...", flush=True)
        report[mode] = run_mode(mode, hosts, args)
        print(f"  CPU {report[mode]['cpu_total_per_s']:.2f} s/s; "
              + "; ".join(f"{bag['host']} {topic.rsplit('/', 2)[-2]}: {t['frames']} frames, {t['gaps']} gaps, cut "
                          f"+{t['start_cut_ms']:.1f}/-{t['stop_cut_ms']:.1f} ms"
                          for bag in report[mode]["bags"] for topic, t in bag["topics"].items()), flush=True)
    report["cpu_ratio_fleet_to_central"] = report["fleet"]["cpu_total_per_s"] / report["central"]["cpu_total_per_s"]
    print(f"fleet CPU / central CPU: {report['cpu_ratio_fleet_to_central']:.2f}")
    if args.results:
        print(f"results: {save(report, 'fleet', Path(args.results))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
