"""S4's codec limit: how many cameras the codec alone allows on this machine's cores.

Why: a largest lossless camera count says little on its own. The codec limit is what the colour conversion and
the encoding alone allow: cores x frame interval / the CPU time one frame costs them, measured in the same run,
through the project's own codec classes (components/image_encoder/codecs.py: ``StillCodec.encode`` of an Image,
``VideoCodec.encode`` of its pixels, what an encoder's worker thread runs per frame) on the frames the cameras
publish (components/photo_content.py at the scenario's size, the sequence number in the first 8 bytes).
Everything else a camera costs (its driver, the encoder's messages, the recorder, the executor) keeps the
lossless count below the limit; S4's target bounds that share (benchmarks/record/targets.py).

**Cold frames.** Each measured frame is written just before it is encoded, so the codec reads it from the caches;
in the rig, a frame waits in memory beside the other cameras' frames and the encoders' reference pictures (more
than the L3 cache holds at a few 1080p cameras). The cost is also measured with each frame pushed out of the
caches first (:data:`EVICT_BYTES` written between the frame and its encoding, outside the timed window): the
difference is what reading the frame from memory adds to the codec, reported beside the limit, never in it.

The cost is CPU time, not wall time: ``time.thread_time`` of the calling thread over ``frames`` frames after
:data:`WARMUP_FRAMES` (the encoder's start and first keyframe), keyframes included at the encoder's interval.
On a machine shared with other processes it grows far less than wall time: waiting for a core is not counted,
only the slowdown of caches and memory bandwidth shared with them. An encoder that works partly on threads of its
own (x265, SVT-AV1, x264 above ``ONE_THREAD_PIXELS``) shows as process CPU time beyond the thread's: there the
process's CPU time is the cost (``clock`` ``process``; this benchmark process runs nothing else meanwhile).
"""
from __future__ import annotations

import os
import time
from array import array
from typing import Any

import numpy as np
from sensor_msgs.msg import Image

from components.image_encoder.codecs import StillCodec, VideoCodec, choose, pixels_of
from components.image_encoder.image_encoder import DEFAULTS as ENCODER_DEFAULTS
from components.photo_content import PhotoContent

#: Frames encoded before the measured ones: the encoder's start and its first keyframe.
WARMUP_FRAMES = 5
#: Process CPU time beyond the thread's by more than this share: the codec works on threads of its own.
OWN_THREADS_SHARE = 0.1
#: Bytes written between a frame and its encoding to push it out of the caches (twice a 32 MiB L3).
EVICT_BYTES = 64 << 20


def codec_limit(ms_per_frame: float, fps: float, cores: int) -> float:
    """Cameras at ``fps`` that ``cores`` allow when each frame costs ``ms_per_frame`` of CPU."""
    return cores * (1000.0 / fps) / ms_per_frame


def photo_frame(photo: PhotoContent, data: array, sequence: int) -> Image:
    """Frame ``sequence`` of a photo camera, as components::CameraDriver publishes it, written into ``data``."""
    photo.fill(sequence, memoryview(data))
    data[0:8] = array("B", sequence.to_bytes(8, "little"))
    image = Image(check_fields=True)
    image.height, image.width, image.encoding, image.step = photo.height, photo.width, "rgb8", photo.width * 3
    image.data = data
    return image


def frame_cost(codec: str, preset: str, width: int, height: int, frames: int, cold: bool = False) -> dict[str, Any]:
    """CPU time per frame of ``codec`` (``preset``; "" the encoder's default) at the encoder's defaults over
    ``frames`` photo frames: the calling thread's, the process's, and the one that counts (module docstring).
    ``cold``: each frame pushed out of the caches before it is encoded."""
    choice = choose(codec, preset, -1, 0, ENCODER_DEFAULTS["keyframe_interval"])
    photo = PhotoContent(width, height, "rgb8")
    data = array("B", bytes(width * height * 3))  # codecs copy what they keep: one buffer serves every frame
    still = None if choice.is_video else StillCodec(choice, 0)
    video = VideoCodec(choice, width, height) if choice.is_video else None
    scratch = np.empty(EVICT_BYTES, np.uint8) if cold else None
    thread_ns = process_ns = 0
    try:
        for sequence in range(WARMUP_FRAMES + frames):
            image = photo_frame(photo, data, sequence)
            if scratch is not None:
                scratch.fill(sequence & 0xFF)
            # the process's window encloses the thread's: its CPU time is never less than the thread's
            process0 = time.process_time_ns()
            thread0 = time.thread_time_ns()
            if video is not None:
                video.encode(pixels_of(image), image.encoding, keyframe=False)
            else:
                still.encode(image)
            thread1 = time.thread_time_ns()
            process1 = time.process_time_ns()
            if sequence >= WARMUP_FRAMES:
                thread_ns += thread1 - thread0
                process_ns += process1 - process0
    finally:
        (video or still).close()
    thread_ms, process_ms = thread_ns / 1e6 / frames, process_ns / 1e6 / frames
    clock = "process" if process_ms > (1 + OWN_THREADS_SHARE) * thread_ms else "thread"
    return {"encoder": choice.encoder, "preset": choice.preset, "quality": choice.quality, "frames": frames,
            "thread_ms_per_frame": thread_ms, "process_ms_per_frame": process_ms, "clock": clock,
            "ms_per_frame": process_ms if clock == "process" else thread_ms}


def measure_limits(codecs: dict[str, tuple[str, str]], width: int, height: int, fps: float,
                   frames: int) -> dict[str, Any]:
    """The codec limit of every ``label: (codec, preset)`` on the cores this process may run on."""
    cores = len(os.sched_getaffinity(0))
    out: dict[str, Any] = {"cores": cores, "frame_interval_ms": 1000.0 / fps, "frames": frames, "codecs": {}}
    for label, (codec, preset) in codecs.items():
        cost = frame_cost(codec, preset, width, height, frames)
        cold = frame_cost(codec, preset, width, height, frames, cold=True)["ms_per_frame"]
        out["codecs"][label] = {**cost, "cameras": codec_limit(cost["ms_per_frame"], fps, cores),
                                "cold_ms_per_frame": cold}
    return out
