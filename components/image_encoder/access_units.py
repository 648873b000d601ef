"""Which ``foxglove_msgs/CompressedVideo`` access units are keyframes, as FFmpeg's bitstream parsers read them.

Why: a bag file must begin each video topic at a keyframe (components/recorder/keyframe_gate.py). The encoders of
the recorder's own container say which of their access units are keyframes; a CompressedVideo topic published by
anything else (another process, a user's component) carries no such flag. FFmpeg's parser of the topic's
``format`` (H.264, H.265, AV1, VP9) reads the access unit's headers and sets the key-frame flag of the packet it
gives back (an IDR or other random-access picture, an AV1 or VP9 key frame), through PyAV's
``CodecContext.parse``: nothing is decoded, and no bitstream is parsed here. About 0.2 ms per 1080p access unit.
"""
from __future__ import annotations

from typing import Any

from components.image_encoder._pyav import av

#: CompressedVideo ``format`` -> FFmpeg's parser (codec) name.
PARSERS = {"h264": "h264", "h265": "hevc", "av1": "av1", "vp9": "vp9"}


class UnknownFormat(ValueError):
    """A CompressedVideo ``format`` FFmpeg has no parser for here."""


def is_keyframe(video_format: str, data: Any) -> bool:
    """Whether the access unit ``data`` (bytes-like) of ``video_format`` is a keyframe: any packet FFmpeg's parser
    makes of it has the key-frame flag. UnknownFormat for a format without a parser."""
    name = PARSERS.get(video_format.strip().lower())
    if name is None:
        raise UnknownFormat(f"format {video_format!r} is none of {', '.join(PARSERS)}")
    parser = av().CodecContext.create(name, "r")  # one per access unit: a parser keeps the unit's end back
    packets = parser.parse(data) + parser.parse(None)  # read in place (buffer protocol); None: the unit is complete
    return any(packet.is_keyframe for packet in packets)
