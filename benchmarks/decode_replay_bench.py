#!/usr/bin/env python3
"""Decoded replay benchmark: ``bag play --decode`` of compressed 1080p30 cameras, per codec and number of streams,
the code of this checkout against a baseline revision's, side by side in one run.

Usage: ``python benchmarks/decode_replay_bench.py [--quick] [--seconds S] [--baseline REV] [--scenarios ...]
[--repeat N] [--fast-rate R]``; the results go to a folder of their own under benchmarks/results/
(``decode_replay.json`` and its tables).

The bags: ``--seconds`` (10) of 1920x1080 photographic frames at 30 Hz per camera (the simulated camera's
``content:=photo``, components/photo_content.py; each camera its own part of the photo), encoded with the image
encoder's own codecs at its defaults (components/image_encoder/codecs.py: H.264 veryfast CRF 23 with a keyframe
every 30 frames, JPEG quality 90) and written with ``BagWriter`` (MCAP) as the recorder writes
``record.compress``: ``/camN/image_raw/video`` (foxglove_msgs/CompressedVideo) and ``/camN/image_raw/compressed``
(sensor_msgs/CompressedImage), the cameras 1 ms apart. Scenarios: one and two streams of H.264 and of JPEG, and
two of each (``mix``). The bags are read once before the runs, so playback reads them from the page cache.

One run: a container started as ``bag play`` runs its own (``--low-latency``, the single executor), a
``components::Player`` loaded with the parameters ``bag play BAG --decode --start-paused --rate R`` gives
(ipc_component/bag_play.py), ``~/resume`` at once, ``~/get_stats`` polled every ``--poll`` s until the player stops
playing. No subscriber: what is measured is reading, decoding and keeping the schedule (a DDS subscriber's
6 MB per frame comes on top). Every scenario runs at rate 1 and at ``--fast-rate`` (20: faster than anything
decodes, so the run shows how fast decoding goes), with the code of ``--baseline`` (its files, from ``git archive``,
imported first through PYTHONPATH: the player before per-stream decoding threads) and with this checkout, one after
the other, ``--repeat`` times; figures are medians over the repeats.

Definitions
-----------
* **lag**: the player's own schedule shifts (``behind.total_s``: each message published more than 10 ms late
  moved the schedule back by its lateness, so the last message went out that much after the bag's span / rate,
  give or take 10 ms);
* **speed**: the bag's span / (span / rate + lag), in times real time (at rate 1 at most 1.0: playback keeps to
  the bag's clock). **wall**: from the ``~/resume`` call to the first poll that found the run ended, so it also
  holds two service calls, up to a poll period and, with decoded topics, the run's head start (its first 0.25 s
  of pictures decoded before its clock starts, docs/player.md);
* **cores**: the container's CPU seconds (every thread: decoders, FFmpeg's own threads, reader, playback) / wall;
  **CPU ms per frame**: those CPU seconds over the frames of all streams (everything the player does for a frame);
* **other**: CPU seconds of other people's processes meanwhile (the machine is shared);
* **complete**: every frame of every stream decoded (``decoded`` of ``~/get_stats``), none failed or skipped.

Target, from this run: the mix (two H.264 and two JPEG 1080p30 streams) plays in real time at rate 1 with this
checkout, every frame decoded: speed at least 0.98 (a lag of at most 2 % of the bag). The ratio against the
baseline's speed is the figure that says what the change did.

Isolation: a random ``ROS_DOMAIN_ID`` (unless set) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` before rclpy
is imported (benchmarks/isolation.py); every process is stopped by its pid, the bags and the baseline's files are
removed, in ``finally`` blocks.
"""
from __future__ import annotations

import isolation  # noqa: F401  (first: the ROS environment before rclpy is imported)

import argparse  # noqa: E402
import contextlib  # noqa: E402
import io  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tarfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Iterator  # noqa: E402

import numpy as np  # noqa: E402
from foxglove_msgs.msg import CompressedVideo  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from rosbag2_interfaces.srv import Resume  # noqa: E402
from sensor_msgs.msg import CompressedImage, Image  # noqa: E402

from baglib.format.metadata import TopicInfo, qos_profile_dict  # noqa: E402
from baglib.write.writer import BagWriter  # noqa: E402
from components.image_encoder import codecs  # noqa: E402
from components.photo_content import PhotoContent  # noqa: E402
from components.sensor_driver import stamp_from_ns  # noqa: E402
from ipc_component.bag_play import add_arguments, player_parameters  # noqa: E402
from benchmarks.record.measure import cpu_seconds, machine_identity, machine_snapshot, other_cpu  # noqa: E402
from benchmarks.record.report import fmt, table  # noqa: E402
from benchmarks.replay_bench import Caller, bench_node, log  # noqa: E402
from benchmarks.result_folder import RESULTS, run_environment, run_header, save  # noqa: E402
from ipc_testing import ContainerClient, ContainerProcess  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
WIDTH, HEIGHT, FPS = 1920, 1080, 30.0
T0_NS = 1_700_000_000_000_000_000
#: Streams per codec of each scenario.
SCENARIOS = {"h264x1": {"h264": 1}, "h264x2": {"h264": 2}, "jpegx1": {"jpeg": 1}, "jpegx2": {"jpeg": 2},
             "mix": {"h264": 2, "jpeg": 2}}
TOPIC_OF = {"h264": "/cam{}/image_raw/video", "jpeg": "/cam{}/image_raw/compressed"}
TARGET_SCENARIO, TARGET_SPEED = "mix", 0.98
#: Frames between the photo windows of two cameras: each camera shows its own part of the photo.
CAMERA_OFFSET = 10_000
RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


# ----------------------------------------------------------------------------------------------- the bags
def encode_streams(codec: str, cameras: int, frames: int) -> list[list[Any]]:
    """Per camera, its ``frames`` messages (CompressedVideo or CompressedImage, stamps set when written)."""
    content = PhotoContent(WIDTH, HEIGHT, "rgb8")
    streams = []
    for camera in range(cameras):
        choice = codecs.choose(codec, "", -1, 0, 30)
        video = codecs.VideoCodec(choice, WIDTH, HEIGHT) if choice.is_video else None
        still = None if choice.is_video else codecs.StillCodec(choice, 0)
        messages = []
        for sequence in range(frames):
            buffer = bytearray(WIDTH * HEIGHT * 3)
            content.fill(sequence + camera * CAMERA_OFFSET, memoryview(buffer))
            if video is not None:
                pixels = np.frombuffer(buffer, np.uint8).reshape(HEIGHT, WIDTH, 3)
                [(_, _, data)] = video.encode(pixels, "rgb8", False)
                messages.append(CompressedVideo(frame_id=f"camera{camera}", format=choice.video_format, data=data))
            else:
                image = Image(height=HEIGHT, width=WIDTH, encoding="rgb8", step=WIDTH * 3, data=bytes(buffer))
                message = CompressedImage(format=still.format_of("rgb8"))
                message.header.frame_id, message.data = f"camera{camera}", still.encode(image)
                messages.append(message)
        if video is not None:
            video.close()
        streams.append(messages)
    return streams


def write_bag(path: Path, streams: dict[str, list[Any]]) -> dict[str, Any]:
    """``streams`` (topic -> messages) as a bag at 30 Hz, the cameras 1 ms apart; what it holds."""
    events = sorted((T0_NS + round(sequence * 1e9 / FPS) + camera * 1_000_000, camera, topic, sequence)
                    for camera, (topic, messages) in enumerate(streams.items()) for sequence in range(len(messages)))
    with BagWriter(path, "mcap") as writer:
        for topic, messages in streams.items():
            msgtype = ("foxglove_msgs/msg/CompressedVideo" if isinstance(messages[0], CompressedVideo)
                       else "sensor_msgs/msg/CompressedImage")
            writer.add_topic(TopicInfo(topic, msgtype, offered_qos_profiles=[qos_profile_dict(RELIABLE)]))
        for log_ns, _camera, topic, sequence in events:
            message = streams[topic][sequence]
            stamp = stamp_from_ns(log_ns)
            if isinstance(message, CompressedVideo):
                message.timestamp = stamp
            else:
                message.header.stamp = stamp
            writer.write(topic, serialize_message(message), log_ns, log_ns)
        files = writer.files
    for file in files:
        with open(file, "rb") as handle:  # read once: playback reads from the page cache
            while handle.read(16 << 20):
                pass
    return {"path": str(path), "topics": list(streams), "frames": len(next(iter(streams.values()))),
            "span_s": (events[-1][0] - events[0][0]) / 1e9, "size_mb": sum(f.stat().st_size for f in files) / 1e6}


def make_bags(workdir: Path, scenarios: list[str], seconds: float) -> dict[str, dict[str, Any]]:
    """One bag per scenario, each camera's stream encoded once and shared by the scenarios that have it."""
    frames = round(seconds * FPS)
    needed = {codec: max(SCENARIOS[s].get(codec, 0) for s in scenarios) for codec in TOPIC_OF}
    encoded: dict[str, list[list[Any]]] = {}
    for codec, cameras in needed.items():
        if cameras:
            log(f"encoding {cameras} x {frames} frames of {codec} ...")
            encoded[codec] = encode_streams(codec, cameras, frames)
    bags = {}
    for scenario in scenarios:
        streams, number = {}, 1
        for codec, cameras in SCENARIOS[scenario].items():
            for camera in range(cameras):
                streams[TOPIC_OF[codec].format(number)] = encoded[codec][camera]
                number += 1
        bags[scenario] = {**write_bag(workdir / scenario, streams), "streams": SCENARIOS[scenario]}
    return bags


# ----------------------------------------------------------------------------------------------- one run
def bag_play_parameters(bag: str, rate: float) -> dict[str, Any]:
    """The player's parameters of ``ipc-component bag play BAG --decode --start-paused --rate RATE``."""
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return player_parameters(parser.parse_args([bag, "--decode", "--start-paused", "--rate", str(rate)]))


def run_once(caller: Caller, client: ContainerClient, pid: int, bag: dict[str, Any], rate: float, name: str,
             args: argparse.Namespace) -> dict[str, Any]:
    """Load a player of ``bag`` at ``rate``, resume it, poll until it stops playing (see the module docstring)."""
    loaded = client.load("components::Player", name=name, parameters=bag_play_parameters(bag["path"], rate),
                         timeout=args.startup_timeout)
    if not loaded.success:
        raise RuntimeError(f"player did not load: {loaded.error_message}")
    try:
        machine0, cpu0 = machine_snapshot(), cpu_seconds(pid)
        started = time.monotonic()
        caller.call(Resume, f"/{name}/resume")
        deadline = started + bag["span_s"] / rate * 4 + 30.0
        while (stats := caller.json(f"/{name}/get_stats"))["playing"]:
            if time.monotonic() > deadline:
                raise TimeoutError("the player did not finish within 4x the bag's span")
            time.sleep(args.poll)
        wall = time.monotonic() - started
        cpu = cpu_seconds(pid) - cpu0
        other_s, _kernel_s = other_cpu(machine0, machine_snapshot(), cpu, {pid, os.getpid()})
    finally:
        client.unload(loaded.unique_id)
    decoded = stats["decoded"]
    complete = all(d["decoded"] == bag["frames"] and not d["failed"] and not d["skipped"] for d in decoded.values())
    lag = stats["behind"]["total_s"]
    return {"rate": rate, "wall_s": wall, "speed": bag["span_s"] / (bag["span_s"] / rate + lag), "lag_s": lag,
            "behind_count": stats["behind"]["count"], "publish_error_ms": stats["publish_error_ms"],
            "queue_starved": stats["queue_starved"], "cpu_s": cpu, "cores": cpu / wall,
            "cpu_ms_per_frame": cpu * 1e3 / (bag["frames"] * len(bag["topics"])), "other_cpu_s": other_s,
            "decoded": decoded, "complete": complete and len(decoded) == len(bag["topics"]),
            "loadavg": os.getloadavg()[0]}


@contextlib.contextmanager
def container(caller: Caller, code: Path | None, name: str, args: argparse.Namespace
              ) -> Iterator[tuple[ContainerClient, int]]:
    """The container ``bag play`` runs in its own process, importing ``code`` first (None: this checkout); its
    working directory is the code's too (``python -m`` puts it before PYTHONPATH)."""
    with ContainerProcess("--low-latency", name=name, cwd=str(code or REPO), code=code) as process:
        try:
            client = ContainerClient(caller.node, f"/{name}")
            client.wait(args.startup_timeout)
            yield client, process.pid
        finally:
            process.stop()


@contextlib.contextmanager
def baseline_code(revision: str, workdir: Path) -> Iterator[Path]:
    """The files of ``revision`` (``git archive``: no worktree, nothing added to the repository)."""
    archive = subprocess.run(["git", "archive", "--format=tar", revision], cwd=REPO, check=True,
                             capture_output=True, timeout=120).stdout
    checkout = workdir / "baseline_code"
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(checkout, filter="data")
    try:
        yield checkout
    finally:
        shutil.rmtree(checkout, ignore_errors=True)


def run_all(caller: Caller, bags: dict[str, dict[str, Any]], codes: dict[str, Path | None],
            args: argparse.Namespace) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """Every scenario, rate and code, ``--repeat`` times; codes alternate, run after run."""
    runs: dict[str, dict[str, list[dict[str, Any]]]] = {s: {c: [] for c in codes} for s in bags}
    with contextlib.ExitStack() as stack:
        containers = {code: stack.enter_context(container(caller, path, f"decode_{code}", args))
                      for code, path in codes.items()}
        number = 0
        for repeat in range(args.repeat):
            for scenario, bag in bags.items():
                for rate in (1.0, args.fast_rate):
                    for code in codes if repeat % 2 == 0 else reversed(codes):
                        number += 1
                        client, pid = containers[code]
                        log(f"[{time.strftime('%H:%M:%S')}] {scenario} rate {rate:g} {code} ...")
                        try:
                            run = run_once(caller, client, pid, bag, rate, f"player_{number}", args)
                        except Exception as exc:  # noqa: BLE001 - recorded as this run's result; the rest runs
                            run = {"rate": rate, "error": f"{type(exc).__name__}: {exc}"}
                        log("    " + (run.get("error") or f"speed {run['speed']:.3f}, lag {run['lag_s']:.3f} s, "
                                                        f"{run['cores']:.2f} cores, complete {run['complete']}"))
                        runs[scenario][code].append(run)
    return runs


# ----------------------------------------------------------------------------------------------- summary
def median_of(runs: list[dict[str, Any]], rate: float, key: str) -> float | None:
    values = [run[key] for run in runs if run["rate"] == rate and "error" not in run]
    return statistics.median(values) if values else None


def summarize(report: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per scenario and code: the medians at rate 1 and at the fast rate, and whether every run was complete."""
    fast = report["config"]["fast_rate"]
    out: dict[str, dict[str, Any]] = {}
    for scenario, by_code in report["runs"].items():
        out[scenario] = {code: {"speed": median_of(runs, 1.0, "speed"), "lag_s": median_of(runs, 1.0, "lag_s"),
                                "wall_s": median_of(runs, 1.0, "wall_s"),
                                "cores": median_of(runs, 1.0, "cores"), "fast_speed": median_of(runs, fast, "speed"),
                                "fast_cores": median_of(runs, fast, "cores"),
                                "cpu_ms_per_frame": median_of(runs, fast, "cpu_ms_per_frame"),
                                "complete": bool(runs) and all(r.get("complete") for r in runs)}
                         for code, runs in by_code.items()}
    return out


def evaluate_target(summary: dict[str, dict[str, Any]]) -> dict[str, str]:
    name = (f"2 H.264 + 2 JPEG 1080p30 streams decoded in real time: speed >= {TARGET_SPEED:g} at rate 1, every "
            "frame decoded")
    current = summary.get(TARGET_SCENARIO, {}).get("current")
    if current is None or current["speed"] is None:
        return {"target": name, "result": "N/A", "detail": f"needs the {TARGET_SCENARIO} scenario"}
    baseline = summary[TARGET_SCENARIO].get("baseline")
    detail = f"speed {current['speed']:.3f}, lag {current['lag_s']:.3f} s, {current['cores']:.2f} cores"
    if baseline and baseline["speed"]:
        detail += (f"; baseline: speed {baseline['speed']:.3f}, lag {baseline['lag_s']:.3f} s, "
                   f"{baseline['cores']:.2f} cores")
    passed = current["speed"] >= TARGET_SPEED and current["complete"]
    return {"target": name, "result": "PASS" if passed else "FAIL", "detail": detail}


def print_report(report: dict[str, Any]) -> None:
    rows = []
    for scenario, by_code in report["summary"].items():
        for code, s in by_code.items():
            rows.append([scenario, code, fmt(s["speed"], ".3f"), fmt(s["lag_s"], ".3f"), fmt(s["wall_s"], ".2f"),
                         fmt(s["cores"], ".2f"),
                         fmt(s["fast_speed"], ".2f"), fmt(s["fast_cores"], ".2f"), fmt(s["cpu_ms_per_frame"], ".1f"),
                         "yes" if s["complete"] else "NO"])
    print("\n" + table(["scenario", "code", "speed at rate 1", "lag s", "wall s", "cores", "fastest (x real time)",
                        "cores",
                        "CPU ms/frame", "complete"], rows))
    target = report["target"]
    print(f"\ntarget: {target['target']}: {target['result']} ({target['detail']})")
    environment = report["environment"]
    print(f"(load average {environment['loadavg_start'][0]:.1f} -> {environment['loadavg_end'][0]:.1f}, "
          f"{environment['cpus']} CPUs; total run time {report['elapsed_s']:.0f} s)")


# ----------------------------------------------------------------------------------------------- main
def scenario_names(text: str) -> list[str]:
    """``--scenarios``: names of SCENARIOS, comma-separated."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = sorted(set(names) - set(SCENARIOS))
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown scenario(s) {', '.join(unknown)}; known: {', '.join(SCENARIOS)}")
    return names


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--quick", action="store_true", help="smoke run: 3 s bags, the one- and four-stream scenarios")
    p.add_argument("--seconds", type=float, default=10.0, help="bag length")
    p.add_argument("--scenarios", type=scenario_names, default=list(SCENARIOS),
                   help=f"comma-separated, of {','.join(SCENARIOS)}")
    p.add_argument("--baseline", metavar="REV", default="",
                   help="also run the code of this git revision ('': this checkout only)")
    p.add_argument("--repeat", type=int, default=1, help="runs of each scenario, rate and code")
    p.add_argument("--fast-rate", type=float, default=20.0, help="the rate of the 'as fast as it decodes' runs")
    p.add_argument("--poll", type=float, default=0.1, help="seconds between ~/get_stats calls")
    p.add_argument("--startup-timeout", type=float, default=60.0)
    p.add_argument("--output-dir", default=None, help="where the temporary bags go (None: $TMPDIR)")
    p.add_argument("--results", default=str(RESULTS),
                   help="the result folder (decode_replay.json and its tables) goes under this directory ('': none)")
    args = p.parse_args(argv)
    if args.quick:
        args.seconds, args.scenarios = min(args.seconds, 3.0), ["h264x1", "jpegx1", "mix"]
    return args


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_arguments(argv)
    started = time.monotonic()
    report: dict[str, Any] = {**run_header("decode_replay_bench.py", argv), "config": vars(args),
                              "environment": {**run_environment(), **machine_identity()},
                              "codes": {"baseline": args.baseline} if args.baseline else {}}
    with bench_node("decode_replay_bench", args.output_dir) as (node, workdir), contextlib.ExitStack() as stack:
        report["bags"] = make_bags(workdir, args.scenarios, args.seconds)
        codes: dict[str, Path | None] = {"current": None}
        if args.baseline:
            codes = {"baseline": stack.enter_context(baseline_code(args.baseline, workdir)), **codes}
        report["runs"] = run_all(Caller(node), report["bags"], codes, args)
    report["elapsed_s"] = time.monotonic() - started
    report["environment"]["loadavg_end"] = os.getloadavg()
    report["summary"] = summarize(report)
    report["target"] = evaluate_target(report["summary"])
    print_report(report)
    if args.results:
        log(f"results: {save(report, 'decode_replay', Path(args.results))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
