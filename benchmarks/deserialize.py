#!/usr/bin/env python3
"""What deserializing a big sensor message costs: rclpy's ``deserialize_message`` vs ``baglib.format.cdr_read``.

Messages: a 1920x1080 rgb8 Image (6.2 MB), a 131072-point PointCloud2 with 16-byte points (2.1 MB) and a
300 kB CompressedImage, each serialized once. ``floor`` is the one copy no deserializer can avoid:
``array('B').frombytes`` of the payload into a fresh array.

The cost of a big copy depends on whether its destination pages are already mapped. By default glibc
malloc soon serves payload-sized buffers from memory freed by the previous call (already faulted in):
that run measures the CPU cost of parsing and copying. Run with ``MALLOC_MMAP_THRESHOLD_=131072`` to
give every payload-sized buffer fresh pages from the kernel, as when a player keeps many messages
queued: then each buffer also costs its page faults (rclpy allocates three per message: the C struct,
a temporary ``bytes`` and the message's array; cdr_read one). The report's first line says which.

Each method runs in blocks of consecutive calls (the first untimed), the blocks of all methods taking
turns ``--rounds`` times so that load from other processes spreads over all of them; consecutive calls
because each method leaves malloc in its own state. Timing excludes freeing the result. Reported per
message and method: the median µs per message over ``--runs`` calls, MB/s of serialized message, the
speed-up over rclpy, and the minor page faults per message.

A second table answers "which way of putting a payload into a ``uint8[]`` field is cheapest": the
Image's payload, given as a memoryview of the CDR buffer, stored into a fresh ``Image().data``.

    [MALLOC_MMAP_THRESHOLD_=131072] python benchmarks/deserialize.py [--runs 60] [--rounds 4] [--output FILE]
"""
from __future__ import annotations

import argparse
import array
import os
import platform
import resource
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CompressedImage, Image, PointCloud2, PointField

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from baglib.format.cdr_read import deserialize  # noqa: E402

Method = Callable[[bytes, type], Any]


def messages() -> list[tuple[str, type, bytes]]:
    """(label, class, CDR bytes) of the three benchmark messages."""
    rng = np.random.default_rng(0)
    image = Image(height=1080, width=1920, encoding="rgb8", step=1920 * 3)
    image.header.frame_id = "camera_optical_frame"
    image.data = rng.integers(0, 256, 1920 * 1080 * 3, dtype=np.uint8).tobytes()
    cloud = PointCloud2(height=64, width=2048, point_step=16, row_step=16 * 2048, is_dense=True)
    cloud.header.frame_id = "lidar"
    cloud.fields = [PointField(name=name, offset=4 * k, datatype=PointField.FLOAT32, count=1)
                    for k, name in enumerate(["x", "y", "z", "intensity"])]
    cloud.data = rng.integers(0, 256, 16 * 131072, dtype=np.uint8).tobytes()
    compressed = CompressedImage(format="jpeg")
    compressed.header.frame_id = "camera"
    compressed.data = rng.integers(0, 256, 300_000, dtype=np.uint8).tobytes()
    return [("Image 1920x1080 rgb8", Image, serialize_message(image)),
            ("PointCloud2 131072 x 16 B", PointCloud2, serialize_message(cloud)),
            ("CompressedImage 300 kB", CompressedImage, serialize_message(compressed))]


def floor(data: bytes, cls: type) -> Method:
    """The payload of ``data`` copied once into a fresh array: the least any deserializer must do."""
    payload = deserialize(data, cls).data.tobytes()
    start = data.rindex(payload)
    stop = start + len(payload)

    def one_copy(data: bytes, cls: type) -> array.array:
        target = array.array("B")
        target.frombytes(memoryview(data)[start:stop])
        return target

    return one_copy


def minor_faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def measure(method: Method, data: bytes, cls: type, calls: int) -> tuple[list[float], int]:
    """µs of each of ``calls`` calls (after one untimed), and the minor page faults of them all."""
    method(data, cls)
    times = []
    faults = 0
    for _ in range(calls):
        before = minor_faults()
        start = time.perf_counter_ns()
        result = method(data, cls)
        times.append((time.perf_counter_ns() - start) / 1000)
        faults += minor_faults() - before
        del result
    return times, faults


def benchmark(runs: int, rounds: int) -> list[str]:
    lines = [f"{'message':<26} {'method':<33} {'µs/msg':>8} {'MB/s':>6} {'speed-up':>8} {'faults/msg':>10}"]
    calls = runs // rounds
    for label, cls, data in messages():
        methods: dict[str, Method] = {
            "rclpy deserialize_message": deserialize_message,
            "cdr_read.deserialize(bytes)": deserialize,
            "cdr_read.deserialize(memoryview)": lambda data, cls: deserialize(memoryview(data), cls),
            "floor: one frombytes copy": floor(data, cls),
        }
        samples: dict[str, list[float]] = {name: [] for name in methods}
        faults = dict.fromkeys(methods, 0)
        for _ in range(rounds):
            for name, method in methods.items():
                times, count = measure(method, data, cls, calls)
                samples[name] += times
                faults[name] += count
        rclpy_us = statistics.median(samples["rclpy deserialize_message"])
        for name, times in samples.items():
            median = statistics.median(times)
            lines.append(f"{label:<26} {name:<33} {median:>8.0f} {len(data) / median:>6.0f} "
                         f"{rclpy_us / median:>7.1f}x {faults[name] / (calls * rounds):>10.0f}")
    return lines


def assignment_table(data: bytes, runs: int) -> list[str]:
    """Ways to store a payload view into a fresh ``Image().data``, median µs."""
    view = memoryview(data)[len(data) - 1920 * 1080 * 3:]

    def frombytes() -> Image:
        msg = Image()
        msg.data.frombytes(view)
        return msg

    def setter_bytes() -> Image:
        msg = Image()
        msg.data = bytes(view)
        return msg

    def slot_array_from_bytes() -> Image:
        msg = Image()
        msg._data = array.array("B", bytes(view))
        return msg

    def setter_memoryview() -> Image:
        msg = Image()
        msg.data = view
        return msg

    def setter_numpy() -> Image:
        msg = Image()
        msg.data = np.frombuffer(view, dtype=np.uint8)
        return msg

    variants = {
        "msg.data.frombytes(view)  [1 copy, used]": (frombytes, runs),
        "msg.data = bytes(view)  [2 copies]": (setter_bytes, runs),
        "msg._data = array('B', bytes(view))  [2 copies]": (slot_array_from_bytes, runs),
        "msg.data = view  [setter iterates]": (setter_memoryview, 3),
        "msg.data = np.frombuffer(view)  [setter iterates]": (setter_numpy, 3),
    }
    lines = ["== storing a 1920x1080x3 payload view into Image().data (median; the slow ones of 3 runs)",
             f"{'assignment':<50} {'µs':>9} {'MB/s':>7}"]
    for name, (function, count) in variants.items():
        times, _ = measure(lambda data, cls: function(), b"", Image, count)
        median = statistics.median(times)
        lines.append(f"{name:<50} {median:>9.0f} {len(view) / median:>7.0f}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=60, help="timed calls per method and message")
    parser.add_argument("--rounds", type=int, default=4, help="blocks the runs are split into")
    parser.add_argument("--output", type=Path, help="also write the report to this file")
    args = parser.parse_args()
    threshold = os.environ.get("MALLOC_MMAP_THRESHOLD_")
    memory = (f"MALLOC_MMAP_THRESHOLD_={threshold}: fresh pages for every big buffer" if threshold
              else "default malloc: big buffers mostly reuse freed memory")
    lines = [f"== deserialize: median of {args.runs // args.rounds * args.rounds} runs; {memory}; "
             f"{platform.python_implementation()} {platform.python_version()}, {platform.machine()}"]
    lines += benchmark(args.runs, args.rounds)
    lines += ["", *assignment_table(messages()[0][2], max(5, args.runs // 5))]
    report = "\n".join(lines)
    print(report)
    if args.output:
        args.output.write_text(report + "\n")


if __name__ == "__main__":
    main()
