"""``bag merge`` throughput against reading its inputs alone, from a cold page cache.

Three inputs (what three computers of a fleet session record) are written with the project's writer, their
messages interleaved in time, in two workloads: ``frames``, camera-sized messages (1080p rgb8, 6.2 MB) with an
IMU-sized one (300 B) every 5 ms, where the bytes dominate; ``small``, 512-byte messages only, where the cost
per message does. For each, with the inputs' cached pages dropped before every pass (fsync, then
``posix_fadvise(DONTNEED)``: no root needed):

* ``read``: each input read alone with the bag reader, one after the other;
* ``merge``: ``merge_bags`` of the three into a new MCAP bag (the timeline's k-way merge plus the writer).

The two take turns, ``--rounds`` times; the medians are reported. MB/s counts the messages' payload bytes. Also
reported: messages per second, and the merge's speed as a share of reading alone.

    python benchmarks/merge_bench.py [--gb 1] [--rounds 3] [--dir DIR] [--quick]
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from baglib.format.metadata import TopicInfo  # noqa: E402
from baglib.read.reader import BagReader  # noqa: E402
from baglib.tools.merge import merge_bags  # noqa: E402
from baglib.write.writer import BagWriter  # noqa: E402
from benchmarks.recover_bench import drop_cache  # noqa: E402
from benchmarks.result_folder import add_location_arguments, run_header, save, work_directory  # noqa: E402

INPUTS = 3
FRAME = 1920 * 1080 * 3
IMU = 300
SMALL = 512
T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def write_input(bag: Path, index: int, workload: str, total_bytes: int) -> None:
    """Input ``index`` of the workload, ``total_bytes`` of payload, its times interleaved with the others'."""
    frame = bytearray(os.urandom(FRAME if workload == "frames" else SMALL))
    imu = os.urandom(IMU)
    with BagWriter(bag) as writer:
        writer.add_topic(TopicInfo("/camera/image_raw" if workload == "frames" else "/small",
                                   "sensor_msgs/msg/Image" if workload == "frames" else "std_msgs/msg/String"))
        if workload == "frames":
            writer.add_topic(TopicInfo("/imu", "sensor_msgs/msg/Imu"))
        for n in range(max(2, total_bytes // len(frame))):
            frame[:8] = n.to_bytes(8, "little")
            if workload == "frames":  # 30 Hz frames, 200 Hz IMU
                t = T0 + n * 33 * MS + index * MS
                writer.write("/camera/image_raw", bytes(frame), t, t)
                for k in range(7):
                    writer.write("/imu", imu, t + k * 5 * MS, t + k * 5 * MS)
            else:  # 2 kHz
                t = T0 + n * MS // 2 + index * 1000
                writer.write("/small", bytes(frame), t, t)


def cold(bags: list[Path]) -> None:
    for bag in bags:
        for path in bag.glob("*.mcap"):
            drop_cache(path)


def read_alone(bags: list[Path]) -> tuple[int, int, float]:
    """Messages, payload bytes and seconds of reading every input alone, one after the other."""
    cold(bags)
    messages = payload = 0
    started = time.perf_counter()
    for bag in bags:
        with BagReader(bag) as reader:
            for message in reader.messages():
                messages += 1
                payload += len(message.data)
    return messages, payload, time.perf_counter() - started


def merge_cold(bags: list[Path], output: Path) -> tuple[int, int, float]:
    """Messages, bytes written and seconds of merging ``bags`` into ``output`` (removed after)."""
    cold(bags)
    started = time.perf_counter()
    report = merge_bags(output, bags)
    seconds = time.perf_counter() - started
    shutil.rmtree(output)
    return report.messages, report.bytes_written, seconds


def measure(workdir: Path, workload: str, total_bytes: int, rounds: int) -> dict[str, Any]:
    """Read alone, then merge, ``rounds`` times in turn; the median of each. (The virtual disk's host may cache
    what the guest dropped: taking turns gives both passes the same chance of it.)"""
    bags = [workdir / f"{workload}_{index}" for index in range(INPUTS)]
    for index, bag in enumerate(bags):
        write_input(bag, index, workload, total_bytes // INPUTS)
    read_s, merge_s = [], []
    for _ in range(rounds):
        messages, payload, seconds = read_alone(bags)
        read_s.append(seconds)
        merged, written, seconds = merge_cold(bags, workdir / f"{workload}_merged")
        assert merged == messages, (merged, messages)
        merge_s.append(seconds)
    for bag in bags:
        shutil.rmtree(bag)
    read, merge = statistics.median(read_s), statistics.median(merge_s)
    return {"inputs": INPUTS, "messages": messages, "payload_bytes": payload, "rounds": rounds,
            "read": {"seconds": read_s, "mb_per_s": payload / read / 1e6, "messages_per_s": messages / read},
            "merge": {"seconds": merge_s, "mb_per_s": payload / merge / 1e6, "messages_per_s": messages / merge,
                      "bytes_written": written},
            "share_of_read": read / merge}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gb", type=float, default=1.0, help="payload of the frames workload, all inputs together "
                                                               "(default 1 GB; small: a tenth of it)")
    parser.add_argument("--quick", action="store_true", help="0.3 GB")
    parser.add_argument("--rounds", type=int, default=3, help="read-alone and merge passes, in turn (default 3)")
    add_location_arguments(parser)
    args = parser.parse_args(argv)
    if args.quick:
        args.gb = 0.3
    report = run_header("merge_bench.py", list(argv if argv is not None else sys.argv[1:]))
    started = time.monotonic()
    with work_directory(args, "merge_bench_") as workdir:
        report["workloads"] = {workload: measure(Path(workdir), workload, int(args.gb * 1e9 * share), args.rounds)
                               for workload, share in (("frames", 1.0), ("small", 0.1))}
    report["elapsed_s"] = time.monotonic() - started
    for workload, entry in report["workloads"].items():
        print(f"{workload:6s}: {entry['messages']} messages, {entry['payload_bytes'] / 1e6:.0f} MB; read alone "
              f"{entry['read']['mb_per_s']:.0f} MB/s, merge {entry['merge']['mb_per_s']:.0f} MB/s "
              f"({entry['share_of_read']:.0%}), {entry['merge']['messages_per_s']:.0f} messages/s")
    if args.results:
        print(f"results: {save(report, 'merge', Path(args.results))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
