#!/usr/bin/env python3
"""What one 1080p camera frame costs the image encoder, per camera pixel format and codec.

Per pair of a format and a codec, ``--frames`` frames of the simulated camera's ``content:=photo`` in that format
(the photograph as rgb8, mono8, YUV 4:2:2 and Bayer, as a camera publishes them; a range image for 16UC1) go
through the encoder's own path as its worker thread runs it (``components.image_encoder.codecs``: ``pixels_of``
and the video codec, or the still codec), without ROS. The pairs run interleaved, frame by frame, in one process,
so that the load of other work on the machine falls on all of them alike. Per pair:

* **CPU ms/frame**: the process's CPU time per frame (``time.process_time``): the calling thread and the
  encoder's own threads (x264's slices);
* **caller ms/frame**: the calling thread's alone (``time.thread_time``): the conversion (swscale), simplejpeg,
  and what the encoder does on the caller's thread;
* **KB/frame** and **% of raw** (of the format's own frame bytes).

The encoder's defaults: H.264 veryfast CRF 23, JPEG quality 90 (4:2:0), PNG and compressedDepth level 3. A frame's
content is written into its buffer before the clock starts.

    python benchmarks/pixel_formats.py [--frames 30] [--size 1920x1080] [--pairs rgb8:h264,yuv422_yuy2:h264,...]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from array import array
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from sensor_msgs.msg import Image  # noqa: E402

from benchmarks.result_folder import add_location_arguments, run_header, save  # noqa: E402
from components.depth_content import DepthContent  # noqa: E402
from components.image_encoder import codecs  # noqa: E402
from components.image_encoder.pixel_formats import FORMATS  # noqa: E402
from components.photo_content import PhotoContent  # noqa: E402

#: The pairs measured by default: each camera format with the codecs it is recorded in.
DEFAULT_PAIRS = ",".join(
    [f"{encoding}:{codec}" for encoding in ("rgb8", "yuv422_yuy2", "yuv422", "bayer_rggb8", "mono8")
     for codec in ("h264", "jpeg", "png")] + ["16UC1:compressedDepth", "16UC1:png"])


@dataclass
class Camera:
    """One format's frame buffer and the content that fills it."""

    image: Any
    content: PhotoContent | DepthContent

    def frame(self, sequence: int) -> Any:
        self.content.fill(sequence, memoryview(self.image.data))
        return self.image


@dataclass
class Pair:
    """A format and a codec, their encoder, and what it cost."""

    encoding: str
    codec: str
    encode: Any
    cpu_ms: list[float] = field(default_factory=list)
    caller_ms: list[float] = field(default_factory=list)
    bytes: int = 0


def camera(encoding: str, width: int, height: int) -> Camera:
    image = Image(check_fields=True)
    image.width, image.height, image.encoding = width, height, encoding
    image.step = width * FORMATS[encoding].bytes_per_pixel
    image.data = array("B", bytes(image.step * height))
    content = DepthContent(width, height) if FORMATS[encoding].is_depth else PhotoContent(width, height, encoding)
    return Camera(image, content)


def encoder(codec: str, width: int, height: int) -> Any:
    """``encode(image) -> bytes`` as the encoder's worker runs it."""
    choice = codecs.choose(codec, "", -1, 0, 30)
    if not choice.is_video:
        return codecs.StillCodec(choice, 0).encode
    video = codecs.VideoCodec(choice, width, height)
    return lambda image: b"".join(unit for _, _, unit in video.encode(codecs.pixels_of(image), image.encoding,
                                                                       keyframe=False))


def measure(pairs: list[Pair], cameras: dict[str, Camera], frames: int) -> None:
    """Every pair's frames, interleaved: frame 0 of each pair, then frame 1 of each, ..."""
    for sequence in range(frames):
        for pair in pairs:
            image = cameras[pair.encoding].frame(sequence)
            process, thread = time.process_time(), time.thread_time()
            data = pair.encode(image)
            pair.caller_ms.append((time.thread_time() - thread) * 1e3)
            pair.cpu_ms.append((time.process_time() - process) * 1e3)
            pair.bytes += len(data)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30, help="frames per pair (default 30)")
    parser.add_argument("--size", default="1920x1080")
    parser.add_argument("--pairs", default=DEFAULT_PAIRS, help="comma-separated encoding:codec")
    add_location_arguments(parser)
    args = parser.parse_args(argv)
    width, height = (int(side) for side in args.size.split("x"))
    report = run_header("pixel_formats.py", list(argv if argv is not None else sys.argv[1:]))
    started = time.monotonic()
    wanted = [item.split(":") for item in args.pairs.split(",")]
    cameras = {encoding: camera(encoding, width, height) for encoding in dict.fromkeys(e for e, _ in wanted)}
    pairs = [Pair(encoding, codec, encoder(codec, width, height)) for encoding, codec in wanted]
    load_before = os.getloadavg()
    measure(pairs, cameras, args.frames)
    report["environment"] = {
        "cpus": os.cpu_count(), "loadavg_start": load_before, "loadavg_end": os.getloadavg(),
        "note": "a machine shared with other work: CPU times are the process's own, but caches and memory "
                "bandwidth are shared; the pairs ran interleaved, so the load fell on all of them alike"}
    report["frames"], report["size"] = args.frames, f"{width}x{height}"
    report["pairs"] = []
    for pair in pairs:
        raw = cameras[pair.encoding].image.step * height
        content = "range image" if FORMATS[pair.encoding].is_depth else "photo"
        entry = {"encoding": pair.encoding, "codec": pair.codec, "content": content,
                 "cpu_ms": round(statistics.fmean(pair.cpu_ms), 2),
                 "cpu_ms_median": round(statistics.median(pair.cpu_ms), 2),
                 "caller_ms": round(statistics.fmean(pair.caller_ms), 2),
                 "kb_per_frame": round(pair.bytes / args.frames / 1e3, 1),
                 "raw_pct": round(100 * pair.bytes / (args.frames * raw), 2)}
        report["pairs"].append(entry)
        print(f"{pair.encoding:>12} {pair.codec:>15}: {entry['cpu_ms']:6.1f} CPU ms/frame ({entry['caller_ms']:5.1f} "
              f"on the caller's thread), {entry['kb_per_frame']:8.1f} KB/frame, {entry['raw_pct']:6.2f} % of raw",
              flush=True)
    report["elapsed_s"] = time.monotonic() - started
    print(f"load average {load_before[0]:.1f} -> {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    if args.results:
        print(f"results: {save(report, 'pixel_formats', Path(args.results))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
