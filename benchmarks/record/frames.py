"""S4's accounting of camera frames by ``header.stamp``, and the PSNR of recorded compressed frames.

A compressed frame carries no sequence number (the driver writes it into the raw pixels, which a lossy codec
changes), but it keeps the raw frame's stamp (CompressedImage ``header.stamp``, CompressedVideo ``timestamp``),
and the driver publishes one CameraInfo with the same stamp beside every frame. So, per camera, within the window:

* **published**: the stamps of its CameraInfo messages and of its frames in the bag (a frame whose CameraInfo
  was lost still counts, and the other way round);
* **recorded**: the distinct stamps of its frames (raw, or compressed by the encoder); **lost** = published -
  recorded: a frame the encoder skipped is lost like one the recorder dropped.

A driver that cannot keep up publishes neither; that shows as published below nominal (``pub_ratio``).

PSNR: the recorded compressed frames are decoded with PyAV (FFmpeg), each matched to the raw frame of the same
stamp recorded in the same bag, over the whole picture: 10 log10(255^2 / MSE), MSE over every sample of every
frame compared.
"""
from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Any, Iterator, Optional

import numpy as np

#: per topic: (stamp ns, serialized bytes) of every message, in the bag's order
Stamps = dict[str, list[tuple[int, int]]]
#: The FFmpeg decoder of each codec's recorded messages.
DECODERS = {"jpeg": "mjpeg", "h264": "h264", "h265": "hevc", "av1": "libdav1d"}


def stamp_of(raw: bytes) -> int:
    """The stamp of a CDR message whose first field is a ``builtin_interfaces/Time`` (every header, and
    CompressedVideo's ``timestamp``), in ns."""
    sec, nanosec = struct.unpack_from("<iI", raw, 4)
    return sec * 1_000_000_000 + nanosec


def read_stamps(bag: Path, keep: set[str], frame_bytes: int, sample: Optional[set[int]] = None
                ) -> tuple[Stamps, dict[str, list[tuple[int, bytes]]], dict[int, bytes]]:
    """Every message's stamp and size by topic; the messages of the topics in ``keep`` whole, in order; and the
    pixels (the last ``frame_bytes`` bytes) of raw frames whose stamp is in ``sample``."""
    from rosbags.rosbag2 import Reader
    stamps: Stamps = {}
    kept: dict[str, list[tuple[int, bytes]]] = {}
    pixels: dict[int, bytes] = {}
    with Reader(bag) as reader:
        for connection, _, raw in reader.messages():
            stamp = stamp_of(raw)
            stamps.setdefault(connection.topic, []).append((stamp, len(raw)))
            if connection.topic in keep:
                kept.setdefault(connection.topic, []).append((stamp, bytes(raw)))
            if sample and stamp in sample and connection.msgtype == "sensor_msgs/msg/Image":
                pixels[stamp] = bytes(raw[len(raw) - frame_bytes:])
    return stamps, kept, pixels


def camera_counts(info: list[tuple[int, int]], frames: list[tuple[int, int]], t0: int, t1: int,
                  fps: float) -> dict[str, Any]:
    """One camera's frames in the window ``[t0, t1]``: published, recorded, lost, bytes (module docstring)."""
    info_in = [(stamp, size) for stamp, size in info if t0 <= stamp <= t1]
    frames_in = [(stamp, size) for stamp, size in frames if t0 <= stamp <= t1]
    info_stamps, frame_stamps = {s for s, _ in info_in}, {s for s, _ in frames_in}
    published = info_stamps | frame_stamps
    nominal = (t1 - t0) / 1e9 * fps
    return {"published": len(published), "recorded": len(frame_stamps), "lost": len(published - frame_stamps),
            "info_lost": len(published - info_stamps), "duplicates": len(frames_in) - len(frame_stamps),
            "frame_bytes": sum(size for _, size in frames_in), "info_bytes": sum(size for _, size in info_in),
            "pub_ratio": len(published) / nominal if nominal else float("nan")}


def sample_stamps(frames: list[tuple[int, int]], t0: int, t1: int, count: int) -> set[int]:
    """At most ``count`` stamps of the window's frames, spread evenly over it."""
    stamps = sorted({stamp for stamp, _ in frames if t0 <= stamp <= t1})
    step = max(1, math.ceil(len(stamps) / max(1, count)))
    return set(stamps[::step])


def decoded_frames(codec: str, messages: list[tuple[int, bytes]], wanted: set[int]) -> Iterator[tuple[int, np.ndarray]]:
    """(stamp, rgb pixels) of the recorded messages whose stamp is in ``wanted``, decoded in recorded order
    (video needs every access unit before). Each packet carries its index as pts, so every decoded frame is
    matched to its own message even where the decoder gave nothing (before the first keyframe) or held frames."""
    import av
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    decoder = av.CodecContext.create(DECODERS[codec], "r")
    packets: list[Any] = []
    for index, (_, raw) in enumerate(messages):
        packet = av.Packet(compressed_data(store, raw, codec))
        packet.pts = index
        packets.append(packet)
    for packet in [*packets, None]:  # None: flush what the decoder holds
        try:
            frames = decoder.decode(packet)
        except av.FFmpegError:  # a video stream joined between keyframes: nothing to decode against yet
            continue
        for frame in frames:
            stamp = messages[frame.pts][0]
            if stamp in wanted:
                yield stamp, frame.to_ndarray(format="rgb24")


def compressed_data(store: Any, raw: bytes, codec: str) -> bytes:
    """The ``data`` of a recorded CompressedImage (JPEG), or of a CompressedVideo parsed from its CDR layout
    (``timestamp``, ``frame_id``, ``data``, ``format``: the type is not in rosbags' store)."""
    if codec == "jpeg":
        return bytes(store.deserialize_cdr(raw, "sensor_msgs/msg/CompressedImage").data)
    frame_id_length = struct.unpack_from("<I", raw, 12)[0]
    offset = 16 + frame_id_length
    offset += -offset % 4
    length = struct.unpack_from("<I", raw, offset)[0]
    return bytes(raw[offset + 4:offset + 4 + length])


def psnr(decoded: dict[int, np.ndarray], raw: dict[int, np.ndarray]) -> dict[str, Any]:
    """PSNR of decoded frames against the raw frames of the same stamps: over all of them (from the mean MSE)
    and the lowest of a single frame; ``frames`` compared, ``unmatched`` raw frames no decoded frame had."""
    errors = [float(np.mean((decoded[stamp].astype(np.float32) - raw[stamp]) ** 2))
              for stamp in sorted(raw) if stamp in decoded]
    to_db = lambda mse: float("inf") if mse == 0 else 10 * math.log10(255.0 ** 2 / mse)  # noqa: E731
    return {"psnr_db": to_db(sum(errors) / len(errors)) if errors else None,
            "psnr_min_db": to_db(max(errors)) if errors else None, "frames": len(errors),
            "unmatched": len(raw) - len(errors)}
