#!/usr/bin/env python3
"""What ``storage.sync_interval`` costs: the S1 rig's data, in real time, through the recorder's write path.

Each run feeds a :class:`RecordingSession` (the recorder's cache, writer thread and BagWriter) with the S1
rig's stream as CDR bytes, paced in real time: two 1920x1080 rgb8 cameras at 30 Hz, a 131072-point LiDAR at
10 Hz and an IMU at 200 Hz (~405 MB/s). Sync intervals are run interleaved (``--rounds`` times each), one bag
each, on the filesystem of ``--output-dir``; reported per interval: process CPU seconds per GB, the
receive-to-write latency p50/p99 (what a sync stalls), and messages dropped. No ROS middleware is involved:
only the file path is measured.

    python benchmarks/sync_cost.py [--seconds 8] [--intervals 0,5,1,0.25] [--storage mcap]
"""
from __future__ import annotations

import argparse
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from baglib.format.metadata import TopicInfo  # noqa: E402
from components.recorder.recorder_options import RecordOptions  # noqa: E402
from components.recorder.recording_session import RecordingSession  # noqa: E402

STREAMS = [  # topic, type, bytes per message, rate (Hz)
    ("/cam0/image_raw", "sensor_msgs/msg/Image", 1920 * 1080 * 3 + 64, 30.0),
    ("/cam1/image_raw", "sensor_msgs/msg/Image", 1920 * 1080 * 3 + 64, 30.0),
    ("/lidar/points", "sensor_msgs/msg/PointCloud2", 131072 * 16 + 200, 10.0),
    ("/imu0/imu", "sensor_msgs/msg/Imu", 328, 200.0),
]


class QuietLogger:
    def info(self, *_: Any) -> None: ...
    warning = error = info


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run(directory: Path, sync_interval: float, seconds: float, storage: str) -> dict[str, Any]:
    options = RecordOptions(storage_id=storage, sync_interval=sync_interval, flush_interval=1.0,
                            max_cache_size=512 * 1024 * 1024)
    session = RecordingSession(options, str(directory / f"sync_{sync_interval:g}_{time.monotonic_ns()}"),
                               QuietLogger())
    for topic, type_name, _, _ in STREAMS:
        session.add_topic(TopicInfo(topic, type_name, "cdr", [], ""))
    payloads = {topic: bytes(size) for topic, _, size, _ in STREAMS}
    schedule = sorted((i / rate, topic) for topic, _, _, rate in STREAMS for i in range(int(seconds * rate)))
    cpu, start = cpu_seconds(), time.monotonic()
    for due, topic in schedule:
        delay = start + due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        now = time.time_ns()
        session.offer(topic, payloads[topic], now, now)
    session.finish(timeout=60.0)
    stats = session.stats()
    used = cpu_seconds() - cpu
    written = stats["bytes_written"]
    shutil.rmtree(session.writer.path, ignore_errors=True)
    latency = stats["write_latency_ms"] or {"p50": float("nan"), "p99": float("nan")}
    return {"cpu_s_per_gb": used / (written / 1e9), "p50_ms": latency["p50"], "p99_ms": latency["p99"],
            "dropped": sum(t["dropped"] for t in stats["topics"].values()), "mb_s": written / 1e6 / seconds}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--intervals", default="0,5,1,0.25", help="sync intervals in seconds (0: never)")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    parser.add_argument("--output-dir", default=str(REPO))
    args = parser.parse_args()
    intervals = [float(x) for x in args.intervals.split(",")]
    results: dict[float, list[dict[str, Any]]] = {interval: [] for interval in intervals}
    with tempfile.TemporaryDirectory(dir=args.output_dir, prefix="sync_cost_") as tmp:
        for _ in range(args.rounds):
            for interval in intervals:
                results[interval].append(run(Path(tmp), interval, args.seconds, args.storage))
    print(f"{args.storage}, S1 data rate, {args.seconds:g} s per run, {args.rounds} rounds interleaved, "
          f"output on {args.output_dir}")
    print("sync_interval  MB/s   CPU s/GB (runs)     write latency p50 / p99 ms (runs)        dropped")
    for interval, runs in results.items():
        cpu = " ".join(f"{r['cpu_s_per_gb']:.3f}" for r in runs)
        latency = " ".join(f"{r['p50_ms']:.1f}/{r['p99_ms']:.1f}" for r in runs)
        mb_s = sum(r["mb_s"] for r in runs) / len(runs)
        print(f"{interval:>13g}  {mb_s:5.0f}  {cpu:18s}  {latency:38s}  {sum(r['dropped'] for r in runs)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
