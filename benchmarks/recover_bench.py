"""``bag recover`` on a large bag a crash cut short: in place against the copying mode, and both against the
disk's own sequential read speed, measured side by side in one run.

A bag of 1080p-sized frames is written with the project's writer, cut inside its last chunk (what a recorder
killed mid-write leaves) and recovered twice from a cold page cache: in place (the default) and into a new
directory (``-o OUT``, the copying mode). Before each, the file's cached pages are dropped (fsync, then
``posix_fadvise(DONTNEED)``: no root needed) and the disk's read speed is measured by reading the same file
once, sequentially. Also reported: the free space the in-place repair used.

Target: in place reads at 80 % or more of the disk's sequential read speed (every byte is read once and only
the tail is written).

    python benchmarks/recover_bench.py [--gb 2] [--dir DIR] [--quick]
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from baglib.format.metadata import TopicInfo  # noqa: E402
from baglib.tools.repair import recover_bag  # noqa: E402
from baglib.write.writer import BagWriter  # noqa: E402
from benchmarks.result_folder import add_location_arguments, run_header, save, work_directory  # noqa: E402

FRAME = 1920 * 1080 * 3
TARGET_SHARE = 0.8
READ_BLOCK = 8 << 20


def write_bag(bag: Path, total_bytes: int) -> Path:
    """A bag of distinct 1080p-sized frames (the first 8 bytes carry the sequence number); its MCAP file."""
    frame = bytearray(os.urandom(FRAME))
    with BagWriter(bag) as writer:
        writer.add_topic(TopicInfo("/camera/image_raw", "sensor_msgs/msg/Image"))
        for n in range(max(2, total_bytes // FRAME)):
            frame[:8] = n.to_bytes(8, "little")
            writer.write("/camera/image_raw", bytes(frame), 1_700_000_000_000_000_000 + n * 33_333_333,
                         1_700_000_000_000_000_000 + n * 33_333_333)
    return next(bag.glob("*.mcap"))


def drop_cache(path: Path) -> None:
    """Make the next read of ``path`` come from the disk."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
        os.posix_fadvise(descriptor, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(descriptor)


def read_speed(path: Path) -> float:
    """MB/s of one cold sequential read of ``path``."""
    drop_cache(path)
    started = time.perf_counter()
    with open(path, "rb", buffering=0) as file:
        while file.read(READ_BLOCK):
            pass
    return path.stat().st_size / (time.perf_counter() - started) / 1e6


def free_bytes(directory: Path) -> int:
    stats = os.statvfs(directory)
    return stats.f_bavail * stats.f_frsize


def recover_cold(bag: Path, output: Path | None) -> dict[str, Any]:
    file = next(bag.glob("*.mcap"))
    size = file.stat().st_size
    drop_cache(file)
    free_before = free_bytes(bag)
    started = time.perf_counter()
    report = recover_bag(bag, output)
    seconds = time.perf_counter() - started
    return {"readable": report.readable, "seconds": seconds, "mb_per_s": size / seconds / 1e6,
            "messages": report.metadata.message_count if report.metadata else 0,
            "extra_bytes": max(0, free_before - free_bytes(bag)), "report": report.text()}


def run(args: argparse.Namespace, workdir: Path) -> dict[str, Any]:
    source = write_bag(workdir / "source", int(args.gb * 1e9))
    size = source.stat().st_size
    cut = size - FRAME // 2  # inside the last frame's chunk
    result: dict[str, Any] = {"bag_bytes": size, "cut_at": cut, "frames": 0}
    for mode in ("in_place", "copy"):
        bag = workdir / mode
        bag.mkdir()
        with open(source, "rb") as src, open(bag / source.name, "wb") as dst:
            shutil.copyfileobj(src, dst, 16 << 20)
            dst.truncate(cut)
        read = read_speed(bag / source.name)
        recovered = recover_cold(bag, None if mode == "in_place" else workdir / f"{mode}_out")
        recovered["disk_read_mb_per_s"] = read
        recovered["share_of_read_speed"] = recovered["mb_per_s"] / read
        result[mode] = recovered
        shutil.rmtree(bag)
        shutil.rmtree(workdir / f"{mode}_out", ignore_errors=True)
    share = result["in_place"]["share_of_read_speed"]
    result["target"] = {"target": f"recover in place at >= {TARGET_SHARE:.0%} of the disk's sequential read speed",
                        "result": "PASS" if share >= TARGET_SHARE and result["in_place"]["readable"] else "FAIL",
                        "detail": f"{result['in_place']['mb_per_s']:.0f} MB/s against a {result['in_place']['disk_read_mb_per_s']:.0f} MB/s "
                                  f"cold read of the same file ({share:.0%})"}
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gb", type=float, default=2.0, help="size of the bag (default 2 GB)")
    parser.add_argument("--quick", action="store_true", help="a 0.5 GB bag")
    add_location_arguments(parser)
    args = parser.parse_args(argv)
    if args.quick:
        args.gb = 0.5
    report = run_header("recover_bench.py", list(argv if argv is not None else sys.argv[1:]))
    with work_directory(args, "recover_bench_") as workdir:
        report.update(run(args, Path(workdir)))
    for mode in ("in_place", "copy"):
        entry = report[mode]
        print(f"{mode:8s}: {entry['mb_per_s']:7.0f} MB/s, {entry['share_of_read_speed']:.0%} of a "
              f"{entry['disk_read_mb_per_s']:.0f} MB/s cold read; {entry['extra_bytes'] / 1e6:.1f} MB extra space; "
              f"{entry['messages']} messages kept")
    print(f"Target ({report['target']['target']}): {report['target']['result']}; {report['target']['detail']}")
    if args.results:
        print(f"results: {save(report, 'recover', Path(args.results))}")
    return 0 if report["target"]["result"] == "PASS" else 1


if __name__ == "__main__":
    sys.exit(main())
