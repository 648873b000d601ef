"""``bag convert`` throughput against reading the bag alone, and a time-window cut against the whole conversion,
from a cold page cache.

One bag is written with the project's writer (MCAP, the recorder's chunks): camera-sized messages (1080p rgb8,
6.2 MB) at 30 Hz with an IMU-sized one (300 B) every 5 ms. Then, with the bag's cached pages dropped before every
pass (fsync, then ``posix_fadvise(DONTNEED)``: no root needed):

* ``read``: the bag read alone with the bag reader;
* ``convert``: ``convert_bags`` of the whole bag into a new MCAP bag (``all_topics``);
* ``cut_input``: the last tenth of its log times, by the input's window (rosbag2 Lyrical's ``--input-options``);
* ``cut_output``: the same tenth by the output's window (rosbag2 Jazzy's ``start_time_ns`` in the output
  options), which here reads only what the window can reach too.

The passes take turns, ``--rounds`` times; the medians are reported. MB/s counts the messages' payload bytes.
Also reported: the conversion's speed as a share of reading alone, and each cut's time as a share of the whole
conversion's (the cut holds a tenth of the messages: about 0.1 when it reads only its chunks).

    python benchmarks/convert_bench.py [--gb 2] [--rounds 3] [--dir DIR] [--quick]
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
from baglib.tools.convert import convert_bags  # noqa: E402
from baglib.tools.convert_options import InputBag, OutputBag  # noqa: E402
from baglib.write.writer import BagWriter  # noqa: E402
from benchmarks.merge_bench import cold, read_alone  # noqa: E402
from benchmarks.result_folder import add_location_arguments, run_header, save, work_directory  # noqa: E402

FRAME = 1920 * 1080 * 3
IMU = 300
T0 = 1_700_000_000_000_000_000
MS = 1_000_000
CUT = 0.1  # the last tenth


def write_bag(bag: Path, total_bytes: int) -> None:
    """``total_bytes`` of frames, 30 Hz, with 200 Hz IMU messages between them."""
    frame = bytearray(os.urandom(FRAME))
    imu = os.urandom(IMU)
    with BagWriter(bag) as writer:
        writer.add_topic(TopicInfo("/camera/image_raw", "sensor_msgs/msg/Image"))
        writer.add_topic(TopicInfo("/imu", "sensor_msgs/msg/Imu"))
        for n in range(max(10, total_bytes // FRAME)):
            frame[:8] = n.to_bytes(8, "little")
            t = T0 + n * 33 * MS
            writer.write("/camera/image_raw", bytes(frame), t, t)
            for k in range(7):
                writer.write("/imu", imu, t + k * 5 * MS, t + k * 5 * MS)


def convert_cold(source: InputBag, output: OutputBag) -> tuple[int, float]:
    """Messages written and seconds of one conversion (its output removed after)."""
    cold([Path(source.uri)])
    started = time.perf_counter()
    report = convert_bags([source], [output])
    seconds = time.perf_counter() - started
    shutil.rmtree(output.uri)
    return report.outputs[0][2], seconds


def measure(workdir: Path, total_bytes: int, rounds: int) -> dict[str, Any]:
    bag = workdir / "bag"
    write_bag(bag, total_bytes)
    with BagReader(bag) as reader:
        start = reader.starting_time_ns + round((1 - CUT) * reader.duration_ns)
    passes: dict[str, tuple[InputBag, OutputBag]] = {
        "convert": (InputBag(str(bag)), OutputBag(str(workdir / "out"), all_topics=True)),
        "cut_input": (InputBag(str(bag), start_time_ns=start), OutputBag(str(workdir / "out"), all_topics=True)),
        "cut_output": (InputBag(str(bag)), OutputBag(str(workdir / "out"), all_topics=True, start_time_ns=start)),
    }
    seconds: dict[str, list[float]] = {name: [] for name in ("read", *passes)}
    counts: dict[str, int] = {}
    for _ in range(rounds):
        messages, payload, elapsed = read_alone([bag])
        seconds["read"].append(elapsed)
        for name, (source, output) in passes.items():
            counts[name], elapsed = convert_cold(source, output)
            seconds[name].append(elapsed)
    assert counts["convert"] == messages, (counts, messages)
    size = sum(path.stat().st_size for path in bag.glob("*.mcap"))
    shutil.rmtree(bag)
    median = {name: statistics.median(values) for name, values in seconds.items()}
    result: dict[str, Any] = {"messages": messages, "payload_bytes": payload, "bag_bytes": size, "rounds": rounds,
                              "cut_share_of_messages": counts["cut_input"] / messages}
    for name, values in seconds.items():
        result[name] = {"seconds": values, "mb_per_s": payload / median[name] / 1e6,
                        "messages_per_s": messages / median[name]}
        if name.startswith("cut"):
            result[name]["messages"] = counts[name]
            result[name]["share_of_convert"] = median[name] / median["convert"]
    result["convert"]["share_of_read"] = median["read"] / median["convert"]
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gb", type=float, default=2.0, help="payload of the bag (default 2 GB)")
    parser.add_argument("--quick", action="store_true", help="0.2 GB")
    parser.add_argument("--rounds", type=int, default=3, help="passes of each kind, in turn (default 3)")
    add_location_arguments(parser)
    args = parser.parse_args(argv)
    if args.quick:
        args.gb = 0.2
    report = run_header("convert_bench.py", list(argv if argv is not None else sys.argv[1:]))
    started = time.monotonic()
    with work_directory(args, "convert_bench_") as workdir:
        report["bag"] = measure(Path(workdir), int(args.gb * 1e9), args.rounds)
    report["elapsed_s"] = time.monotonic() - started
    entry = report["bag"]
    print(f"{entry['messages']} messages, {entry['payload_bytes'] / 1e6:.0f} MB: read alone "
          f"{entry['read']['mb_per_s']:.0f} MB/s, convert {entry['convert']['mb_per_s']:.0f} MB/s "
          f"({entry['convert']['share_of_read']:.0%} of reading); the last {CUT:.0%} cut by the input's window in "
          f"{entry['cut_input']['share_of_convert']:.0%} of the conversion's time, by the output's in "
          f"{entry['cut_output']['share_of_convert']:.0%}")
    if args.results:
        print(f"results: {save(report, 'convert', Path(args.results))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
