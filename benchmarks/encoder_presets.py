#!/usr/bin/env python3
"""What one 1080p photo frame costs each video encoder preset: time, CPU, bytes against raw, PSNR.

The encoder is the one ``components::ImageEncoder`` uses (``components.image_encoder.codecs``: the same
options, CRF, no B-frames, no look-ahead, keyframes every ``--keyframe-interval`` frames), fed ``--frames``
frames of the simulated camera's photo content (``components.photo_content``, what ``content:=photo`` publishes)
one after the other, as fast as it takes them; no ROS. Per codec and preset:

* **ms/frame**: wall time of one ``encode`` call (median and 95th percentile). The encoder's own threads count
  in the wall time, so on a machine with fewer free cores than the encoder uses this grows with the load;
* **CPU ms/frame**: CPU time of this process per frame (every thread: the encoder's too);
* **% raw**: encoded bytes over the frames' raw bytes (``width * height * 3``);
* **PSNR**: of the decoded frames (PyAV) against the frames encoded, over all of them;
* **1080p30 cameras per core**: 1000 / (CPU ms/frame * 30).

Which preset is the default (codecs.DEFAULT_PRESET) follows from these numbers: for x264 the cheapest per frame
that keeps S4's targets (at least 36 dB, at most 3 % of the raw bytes), so that the most cameras fit the cores.

    python benchmarks/encoder_presets.py [--frames 90] [--codecs h264:ultrafast,h264:superfast,...]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import av
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from components.image_encoder.codecs import VideoCodec, choose  # noqa: E402
from components.image_encoder.decoding import VIDEO_DECODERS  # noqa: E402
from components.photo_content import PhotoContent  # noqa: E402

DEFAULT_CODECS = ("h264:ultrafast,h264:superfast,h264:veryfast,h265:ultrafast,h265:superfast,av1:10,av1:12")


def frames(width: int, height: int, count: int) -> list[np.ndarray]:
    """The camera's first ``count`` photo frames (with its sequence number in the first 8 bytes, as published)."""
    photo = PhotoContent(width, height, "rgb8")
    out = []
    for sequence in range(count):
        buffer = bytearray(width * height * 3)
        photo.fill(sequence, memoryview(buffer))
        buffer[0:8] = sequence.to_bytes(8, "little")
        out.append(np.frombuffer(buffer, np.uint8).reshape(height, width, 3))
    return out


def psnr(mse: float) -> float:
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def measure(codec: str, preset: str, pictures: list[np.ndarray], keyframe_interval: int) -> dict:
    """Encode ``pictures`` with the encoder's settings, then decode them again and compare."""
    height, width = pictures[0].shape[:2]
    encoder = VideoCodec(choose(codec, preset, -1, 0, keyframe_interval), width, height)
    times, units = [], []
    cpu_before = time.process_time()
    for picture in pictures:
        started = time.perf_counter()
        units += [unit for _, _, unit in encoder.encode(picture, "rgb8", keyframe=False)]
        times.append((time.perf_counter() - started) * 1e3)
    cpu_ms = (time.process_time() - cpu_before) * 1e3 / len(pictures)
    encoder.close()
    decoder = av.CodecContext.create(VIDEO_DECODERS[codec], "r")
    packets = [av.Packet(unit) for unit in units] + [None]  # None: flush the decoder's delayed frames
    decoded = [frame.to_ndarray(format="rgb24") for packet in packets for frame in decoder.decode(packet)]
    if len(decoded) != len(pictures):
        raise RuntimeError(f"{codec} {preset}: {len(decoded)} frames decoded of {len(pictures)}")
    mse = statistics.fmean(float(np.mean((a.astype(np.float32) - b) ** 2)) for a, b in zip(decoded, pictures))
    times.sort()
    return {"codec": codec, "preset": preset, "frames": len(pictures), "ms_median": round(statistics.median(times), 1),
            "ms_p95": round(times[int(0.95 * (len(times) - 1))], 1), "cpu_ms_per_frame": round(cpu_ms, 1),
            "raw_pct": round(100 * sum(map(len, units)) / (len(pictures) * width * height * 3), 2),
            "psnr_db": round(psnr(mse), 2), "cameras_per_core_30hz": round(1000 / (cpu_ms * 30), 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=90)
    parser.add_argument("--size", default="1920x1080")
    parser.add_argument("--keyframe-interval", type=int, default=30)
    parser.add_argument("--codecs", default=DEFAULT_CODECS, help="comma-separated codec:preset")
    parser.add_argument("--json", help="write the rows to this file")
    args = parser.parse_args()
    width, height = (int(side) for side in args.size.split("x"))
    pictures = frames(width, height, args.frames)
    print(f"{args.frames} frames {width}x{height} photo content, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.2f}", flush=True)
    rows = []
    for item in args.codecs.split(","):
        codec, _, preset = item.partition(":")
        row = measure(codec, preset, pictures, args.keyframe_interval)
        rows.append(row)
        print(f"{codec:>5} {preset:>10}: {row['ms_median']:6.1f} ms/frame median, {row['ms_p95']:6.1f} p95, "
              f"{row['cpu_ms_per_frame']:6.1f} CPU ms/frame, {row['raw_pct']:5.2f} % of raw, "
              f"{row['psnr_db']:5.2f} dB, {row['cameras_per_core_30hz']:.2f} cameras at 30 Hz per core", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
