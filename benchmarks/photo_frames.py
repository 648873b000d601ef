#!/usr/bin/env python3
"""What building one camera frame costs, random against photographic content (``content:=photo``).

One :class:`~components.camera_driver.CameraDriver` per content builds ``--frames`` frames with ``make_image``
(no publishing, no DDS), each released before the next as a recorder would, so buffers are reused as in a
running rig. Reported per content and size: the CPU time of a frame (median and 95th percentile of the
thread's CPU clock), the camera's one-off load time, the memory its prepared content takes, and how many
cameras at ``--fps`` one core could feed. A photo frame is one numpy add of a photo slice and a noise slice.

    python benchmarks/photo_frames.py [--frames 300] [--sizes 1920x1080,640x480] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from components.camera_driver import CameraDriver  # noqa: E402


def measure(context: Context, content: str, width: int, height: int, frames: int) -> dict:
    """Load a camera of ``content`` and time ``frames`` frames of it."""
    started = time.perf_counter()
    camera = CameraDriver(f"bench_{content}_{width}", context=context, parameter_overrides=[
        Parameter("width", value=width), Parameter("height", value=height), Parameter("content", value=content)])
    load_s = time.perf_counter() - started
    try:
        costs = []
        for sequence in range(frames):
            before = time.thread_time_ns()
            image = camera.make_image(sequence, 0)
            costs.append((time.thread_time_ns() - before) / 1e6)
            del image
        prepared = (sum(level.nbytes for level in camera._photo.levels) + camera._photo.noise.nbytes
                    if camera._photo is not None else len(camera._pool))
    finally:
        camera.destroy_node()
    costs.sort()
    median = statistics.median(costs)
    return {"content": content, "size": f"{width}x{height}", "frames": frames, "ms_median": round(median, 3),
            "ms_p95": round(costs[int(0.95 * (len(costs) - 1))], 3), "load_s": round(load_s, 2),
            "prepared_mb": round(prepared / 1e6, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--sizes", default="1920x1080,640x480")
    parser.add_argument("--fps", type=float, default=30.0, help="rate for the cameras-per-core column")
    parser.add_argument("--json", help="write the rows to this file")
    args = parser.parse_args()
    context = Context()
    rclpy.init(context=context)
    rows = []
    try:
        for size in args.sizes.split(","):
            width, height = (int(side) for side in size.split("x"))
            for content in ("random", "photo"):
                row = measure(context, content, width, height, args.frames)
                row["cameras_per_core"] = int(1000.0 / (row["ms_median"] * args.fps))
                rows.append(row)
                print(f"{row['size']:>10} {content:>6}: {row['ms_median']:.3f} ms/frame median, "
                      f"{row['ms_p95']:.3f} p95; load {row['load_s']} s; prepared {row['prepared_mb']} MB; "
                      f"{row['cameras_per_core']} cameras at {args.fps:g} Hz per core", flush=True)
    finally:
        rclpy.shutdown(context=context)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
