"""The way back: ``sensor_msgs/CompressedImage`` and ``foxglove_msgs/CompressedVideo`` into ``sensor_msgs/Image``.

The same libraries as the encoder (codecs.py), no codec or bitstream parser of our own: libjpeg-turbo (simplejpeg)
for JPEG, FFmpeg (PyAV) for PNG and video. Both release the GIL while they decode.

* Stills: the pixels come back in the encoding the ``format`` string names first, as image_transport's
  ``compressed`` subscriber does (``"rgb8; jpeg compressed bgr8"`` was an ``rgb8`` image, ``"16UC1; png
  compressed "`` a 16-bit one); a ``format`` that names none (``"jpeg"``, Foxglove's form) gives what OpenCV's
  decoder would: ``bgr8`` (``bgra8`` for a PNG with alpha) or ``mono8`` for a grey picture. The header is the
  compressed message's.
* compressedDepth (``"16UC1; compressedDepth png"``): the PNG after image_transport's configuration header
  (compressed_depth.py), back to the very samples encoded, as its compressedDepth subscriber gives them.
* Video: one :class:`VideoDecoder` per stream, fed one access unit per message in recorded order; each gives
  one ``rgb8`` image stamped with the message's ``timestamp`` and ``frame_id`` (streams without B-frames, as
  Foxglove requires of CompressedVideo: a frame out for every frame in). A decoder starts at a keyframe: until
  one arrives it gives nothing, and the frames before it are counted as skipped (a playback that starts or
  seeks into the middle of a group of pictures).
"""
from __future__ import annotations

from array import array
from dataclasses import dataclass
from typing import Any

import numpy as np
import simplejpeg
from sensor_msgs.msg import Image

from components.image_encoder import compressed_depth
from components.image_encoder._pyav import av
from components.image_encoder.codecs import JPEG_INPUTS
from components.image_encoder.pixel_formats import FORMATS

#: CompressedVideo ``format`` -> FFmpeg decoder.
VIDEO_DECODERS = {"h264": "h264", "h265": "hevc", "av1": "libdav1d"}
#: PyAV pixel format -> the encoding OpenCV's decoder gives for a picture whose ``format`` names no encoding.
_UNNAMED_PNG = {"gray": "mono8", "rgba": "bgra8", "ya8": "bgra8", "gray16be": "mono16"}
#: How a kind of still is named in messages.
_KIND_NAMES = {"jpeg": "JPEG", "png": "PNG"}
#: The encodings a still decodes to: those a picture holds as they are (a Bayer mosaic in PNG; not YUV, which
#: comes back rgb8).
DECODED = [encoding for encoding, layout in FORMATS.items() if not layout.converted_as or layout.is_mosaic]


class DecodeError(ValueError):
    """A message the decoder cannot turn into an image (its format, or damaged data)."""


@dataclass
class DecodeCounts:
    """What one stream's decoder did with the messages it got (each ends in exactly one of the three)."""

    decoded: int = 0
    skipped: int = 0   # video before its first keyframe: nothing to decode it against
    failed: int = 0    # data the decoder refused, or a format it does not know


def image_message(stamp: Any, frame_id: str, pixels: np.ndarray | Any, width: int, height: int,
                  encoding: str) -> Image:
    """A ``sensor_msgs/Image`` owning a copy of ``pixels`` (rows without padding), made with one copy."""
    bytes_per_pixel = FORMATS[encoding].bytes_per_pixel
    data = array("B")
    data.frombytes(np.ascontiguousarray(pixels).view(np.uint8) if isinstance(pixels, np.ndarray) else pixels)
    message = Image(check_fields=True)
    message.header.stamp, message.header.frame_id = stamp, frame_id
    message.height, message.width, message.encoding = height, width, encoding
    message.step = width * bytes_per_pixel
    message.data = data  # check_fields=True keeps the array as it is (no second copy)
    return message


def still_kind(format_: str) -> str:
    """``jpeg``, ``png`` or ``compressedDepth`` from a CompressedImage ``format`` (image_transport's or Foxglove's
    form)."""
    if compressed_depth.is_compressed_depth(format_):
        return compressed_depth.TRANSPORT
    compression = format_.lower()
    if "png" in compression:
        return "png"
    if "jpeg" in compression or "jpg" in compression:
        return "jpeg"
    raise DecodeError(f"format {format_!r} is neither JPEG nor PNG")


def named_encoding(format_: str) -> str:
    """The original encoding a ``format`` string names (``"rgb8; jpeg compressed bgr8"`` -> rgb8), else ""."""
    first, separator, _ = format_.partition(";")
    return first.strip() if separator and first.strip() in DECODED else ""


class StillDecoder:
    """JPEG, PNG and compressedDepth pictures of one topic.

    Each PNG gets an FFmpeg decoder of its own (a few microseconds): one decoder kept between pictures gave every
    picture after the first wrong, its rows offset by the picture before (measured with FFmpeg 8's PNG decoder
    through PyAV, 8 and 16 bits).
    """

    def decode(self, message: Any) -> Image:
        data = message.data
        kind = still_kind(message.format)
        encoding = named_encoding(message.format)
        try:
            if kind == "jpeg":
                return self._jpeg(message, data, encoding)
            if kind == compressed_depth.TRANSPORT:
                data = compressed_depth.png_of(message.format, data)
            return self._png_image(message, data, encoding)
        except (ValueError, av().FFmpegError) as exc:
            raise DecodeError(f"{_KIND_NAMES.get(kind, kind)} data cannot be decoded: {exc}") from None

    @staticmethod
    def _jpeg(message: Any, data: Any, encoding: str) -> Image:
        height, width, colourspace, _ = simplejpeg.decode_jpeg_header(data)
        if not encoding:
            encoding = "mono8" if colourspace == "Gray" else "bgr8"
        if FORMATS[encoding].is_depth:
            raise DecodeError(f"format {message.format!r}: a JPEG holds no 16-bit samples")
        pixels = simplejpeg.decode_jpeg(data, JPEG_INPUTS[FORMATS[encoding].samples_format][0])
        return image_message(message.header.stamp, message.header.frame_id, pixels, width, height, encoding)

    @staticmethod
    def _png_image(message: Any, data: Any, encoding: str) -> Image:
        frames = av().CodecContext.create("png", "r").decode(av().Packet(bytes(data)))
        if not frames:
            raise DecodeError("PNG data gave no picture")
        frame = frames[-1]
        if not encoding:
            encoding = _UNNAMED_PNG.get(frame.format.name, "bgr8")
        pixels = frame.to_ndarray(format=FORMATS[encoding].samples_format)
        return image_message(message.header.stamp, message.header.frame_id, pixels, frame.width, frame.height,
                             encoding)


class VideoDecoder:
    """One video stream's FFmpeg decoder; :meth:`decode` gives an ``rgb8`` Image, or None before a keyframe."""

    def __init__(self, video_format: str) -> None:
        decoder = VIDEO_DECODERS.get(video_format)
        if decoder is None:
            raise DecodeError(f"video format {video_format!r} is not one of {', '.join(VIDEO_DECODERS)}")
        self.video_format = video_format
        self._context = av().CodecContext.create(decoder, "r")
        # One frame out per frame in: FFmpeg's frame threads (and dav1d's) would hold frames back.
        self._context.thread_type = "SLICE"
        if decoder == "libdav1d":
            self._context.options = {"max_frame_delay": "1"}
        # One colour converter for the stream: a frame's own reformat() sets up FFmpeg's scaler for every frame.
        self._to_rgb = av().video.reformatter.VideoReformatter()
        self._started = False

    def decode(self, message: Any) -> Image | None:
        """The picture of one access unit; None while the stream has not reached a keyframe (what the decoder
        refuses before one, lacking the parameter sets, is waiting too). DecodeError for data it refuses after
        one (the stream then waits for the next keyframe again)."""
        if message.format != self.video_format:
            raise DecodeError(f"format {message.format!r} in a {self.video_format} stream")
        try:
            frames = self._context.decode(av().Packet(bytes(message.data)))
        except av().FFmpegError as exc:
            if not self._started:
                return None
            self._started = False
            raise DecodeError(f"{self.video_format} data cannot be decoded: {exc}") from None
        picture = None
        for frame in frames:
            self._started = self._started or frame.key_frame
            if self._started:
                picture = frame
        if picture is None:
            return None
        rgb = self._to_rgb.reformat(picture, format="rgb24")
        plane = rgb.planes[0]
        pixels = plane if plane.line_size == rgb.width * 3 else rgb.to_ndarray()
        return image_message(message.timestamp, message.frame_id, pixels, rgb.width, rgb.height, "rgb8")
