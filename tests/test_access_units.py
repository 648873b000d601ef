"""Keyframes of CompressedVideo access units as FFmpeg's parsers read them (components/image_encoder/access_units.py),
against what the encoder that made each unit says of it: x264, x265 and SVT-AV1 through the ImageEncoder's own
codec class, libvpx's VP9 through PyAV."""
from __future__ import annotations

import fractions

import av
import numpy as np
import pytest

from components.image_encoder.access_units import UnknownFormat, is_keyframe
from components.image_encoder.codecs import VideoCodec, choose

WIDTH, HEIGHT, FRAMES, INTERVAL = 64, 48, 12, 5


def frames() -> list[np.ndarray]:
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    return [np.stack([(x * 3 + 7 * n) % 256, (y * 5 + n) % 256, (x + y) % 256], -1).astype(np.uint8)
            for n in range(FRAMES)]


def units_of(codec: str) -> list[tuple[bool, bytes]]:
    """(the encoder's keyframe flag, the access unit) of FRAMES frames, a keyframe every INTERVAL."""
    if codec == "vp9":
        context = av.CodecContext.create("libvpx-vp9", "w")
        context.width, context.height, context.pix_fmt = WIDTH, HEIGHT, "yuv420p"
        context.time_base, context.gop_size = fractions.Fraction(1, 30), INTERVAL
        context.options = {"lag-in-frames": "0", "deadline": "realtime"}
        units = []
        for pts, pixels in enumerate(frames()):
            frame = av.VideoFrame.from_ndarray(pixels, format="rgb24").reformat(format="yuv420p")
            frame.pts = pts
            units += [(packet.is_keyframe, bytes(packet)) for packet in context.encode(frame)]
        return units + [(packet.is_keyframe, bytes(packet)) for packet in context.encode(None)]
    video = VideoCodec(choose(codec, "", -1, 0, INTERVAL), WIDTH, HEIGHT)
    return [(keyframe, data) for pixels in frames() for _, keyframe, data in video.encode(pixels, "rgb8", False)]


@pytest.mark.parametrize("codec", ["h264", "h265", "av1", "vp9"])
def test_the_parser_finds_the_keyframes_the_encoder_made(codec: str) -> None:
    units = units_of(codec)
    assert len(units) == FRAMES
    flags = [keyframe for keyframe, _ in units]
    assert flags.count(True) >= FRAMES // INTERVAL and flags[0], flags  # the test means something
    assert [is_keyframe(codec.upper(), data) for _, data in units] == flags


def test_a_format_without_a_parser_is_named() -> None:
    with pytest.raises(UnknownFormat, match="format 'mjpeg' is none of h264, h265, av1, vp9"):
        is_keyframe("mjpeg", b"\xff\xd8")
