"""image_transport's ``compressedDepth`` format: a 12-byte configuration header, then a 16-bit PNG.

What compressed_depth_image_transport (ros-perception/image_transport_plugins, ``codec.cpp``) writes for 16-bit
depth, so that its subscriber decodes what the image encoder publishes: ``format`` is
``"<encoding>; compressedDepth png"``, and ``data`` begins with its ``ConfigHeader`` (``compression_common.h``:
``enum compressionFormat format; float depthParam[2]``, 12 bytes in the machine's byte order, little-endian where
ROS runs), whose ``format`` is ``INV_DEPTH`` (0) and whose quantisation parameters serve 32-bit float depth only
(0 here; upstream's decoder reads them for 32-bit images alone). The PNG holds the samples as they are: unlike
upstream's publisher, which zeroes every value beyond its ``depth_max`` (10 m by default), nothing is dropped.

Only the header is written or skipped here; the PNG is FFmpeg's (codecs.py, decoding.py).
"""
from __future__ import annotations

import struct

#: ``ConfigHeader``: the compression format (an int-sized enum) and two floats.
HEADER = struct.Struct("<iff")
#: ``compressionFormat::INV_DEPTH``, the value upstream's publisher writes for every image.
INV_DEPTH = 0
#: The part of ``format`` that names the transport (``"16UC1; compressedDepth png"``).
TRANSPORT = "compressedDepth"


def format_string(encoding: str) -> str:
    """``format`` of a compressedDepth message of an ``encoding`` image, as upstream's publisher writes it."""
    return f"{encoding}; {TRANSPORT} png"


def header() -> bytes:
    """The configuration header that precedes the PNG."""
    return HEADER.pack(INV_DEPTH, 0.0, 0.0)


def is_compressed_depth(format_: str) -> bool:
    """Whether a CompressedImage ``format`` is compressedDepth's."""
    return TRANSPORT in format_


def png_of(format_: str, data: bytes) -> bytes:
    """The PNG of a compressedDepth message; ValueError for what upstream's subscriber would not read as a PNG
    of 16-bit depth (RVL, 32-bit float depth, data no longer than the header)."""
    encoding, _, compression = format_.partition(";")
    if f"{TRANSPORT} " in compression and f"{TRANSPORT} png" not in compression:
        raise ValueError(f"format {format_!r}: only compressedDepth's PNG is decoded here (RVL has no decoder in "
                         "FFmpeg)")
    if encoding.strip() not in ("16UC1", "mono16"):
        raise ValueError(f"format {format_!r}: only 16-bit depth (16UC1, mono16) is decoded here, not quantised "
                         "32-bit float depth")
    if len(data) <= HEADER.size:
        raise ValueError(f"a compressedDepth message holds its {HEADER.size}-byte header and a PNG; this one has "
                         f"{len(data)} bytes")
    return bytes(data[HEADER.size:])
