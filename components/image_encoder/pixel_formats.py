"""The ``sensor_msgs/Image`` encodings the image encoder takes, and how FFmpeg reads each one.

A camera's pixels reach the codecs without a conversion of ours: this table tells, per encoding, what FFmpeg calls
its bytes, so that FFmpeg's swscale converts straight from them to what a codec takes. A YUV 4:2:2 camera
(``yuv422_yuy2``/``yuyv`` = YUYV, ``yuv422``/``uyvy`` = UYVY, as sensor_msgs' image_encodings and usb_cam name them)
goes to the video encoders' 4:2:0 without an RGB pass; a Bayer camera (``bayer_rggb8`` ...) is demosaiced to RGB
by swscale for video and JPEG, and kept as its mosaic in PNG; 16-bit depth (``16UC1``, ``mono16``) is stored
lossless as 16-bit PNG.

Every frame is checked first (:func:`pixels_of`): its pixels are a numpy view of the message's own buffer, and a
frame that is not what its header says (unknown encoding, too little data, a step shorter than a row, no pixels, a
size its layout cannot have) is an :class:`EncodeError` that begins with the image (``a 640x480 rgb8 image ...``)
and says what is wrong, never a library's own words.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from components.image_encoder._pyav import av

if TYPE_CHECKING:
    from av import VideoFrame


class EncodeError(ValueError):
    """A frame this codec cannot take (its encoding or size); the frame is counted as rejected."""


@dataclass(frozen=True)
class PixelFormat:
    """How the bytes of one encoding are read, and what each codec is handed."""

    av_format: str           # FFmpeg's name for the bytes (16-bit: little-endian; big-endian images: gray16be)
    bytes_per_pixel: int     # the last axis of the numpy view (a 4:2:2 pixel: Y and one of U, V)
    jpeg_input: str          # the FFmpeg pixel format simplejpeg is handed (yuv420p: its planes; "": none fits)
    png_format: str          # what the PNG stores: the samples where PNG holds them (a Bayer mosaic: grey), else RGB
    converted_as: str = ""   # a still whose colours FFmpeg converted is named this (rgb8) instead of the encoding
    block: tuple[int, int] = (1, 1)  # width and height are multiples of these: 4:2:2 pairs, Bayer cells

    @property
    def is_depth(self) -> bool:
        """16-bit single-channel samples: lossless PNG only, never 8-bit JPEG or 4:2:0 video."""
        return self.png_format == "gray16be"

    @property
    def is_mosaic(self) -> bool:
        """A Bayer mosaic: one colour per pixel, which PNG stores as it is (grey) and everything else demosaics."""
        return self.av_format.startswith("bayer_")

    @property
    def samples_format(self) -> str:
        """FFmpeg's name for the samples as they are, one per byte for a mosaic (what a PNG of them holds)."""
        return "gray" if self.is_mosaic else self.av_format


_YUYV = PixelFormat("yuyv422", 2, "yuv420p", "rgb24", "rgb8", (2, 1))
_UYVY = PixelFormat("uyvy422", 2, "yuv420p", "rgb24", "rgb8", (2, 1))
_DEPTH = PixelFormat("gray16le", 2, "", "gray16be")
#: sensor_msgs encoding -> its format (yuv422 and yuv422_yuy2 are the deprecated names of uyvy and yuyv).
FORMATS: dict[str, PixelFormat] = {
    "rgb8": PixelFormat("rgb24", 3, "rgb24", "rgb24"), "bgr8": PixelFormat("bgr24", 3, "bgr24", "rgb24"),
    "rgba8": PixelFormat("rgba", 4, "rgba", "rgba"), "bgra8": PixelFormat("bgra", 4, "bgra", "rgba"),
    "mono8": PixelFormat("gray", 1, "gray", "gray"),
    "yuv422_yuy2": _YUYV, "yuyv": _YUYV, "yuv422": _UYVY, "uyvy": _UYVY,
    **{f"bayer_{order}8": PixelFormat(f"bayer_{order}8", 1, "rgb24", "gray", "rgb8", (2, 2))
       for order in ("rggb", "bggr", "gbrg", "grbg")},
    "16UC1": _DEPTH, "mono16": _DEPTH,
}


def describe(image: Any) -> str:
    """How a rejection names an image: ``a 640x480 rgb8 image``."""
    return f"a {image.width}x{image.height} {image.encoding or '(no encoding)'} image"


def format_of(image: Any) -> PixelFormat:
    """The format of ``image``'s encoding; EncodeError for one the encoder does not take."""
    found = FORMATS.get(image.encoding)
    if found is None:
        raise EncodeError(f"{describe(image)}: encoding {image.encoding!r} is not one the encoder takes "
                          f"({', '.join(FORMATS)})")
    return found


def pixels_of(image: Any) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` as a (height, width, bytes per pixel) uint8 view of its own data
    buffer (no copy), after checking that the message holds what its header says."""
    layout = format_of(image)
    height, width, step = image.height, image.width, image.step
    row = width * layout.bytes_per_pixel
    if not width or not height:
        raise EncodeError(f"{describe(image)} has no pixels")
    if width % layout.block[0] or height % layout.block[1]:
        raise EncodeError(f"{describe(image)}: {image.encoding} comes in cells of {layout.block[0]}x{layout.block[1]} "
                          "pixels, so its width and height are multiples of them")
    if step < row:
        raise EncodeError(f"{describe(image)} has rows of {row} bytes, longer than its step of {step}")
    if len(image.data) < step * height:
        raise EncodeError(f"{describe(image)} needs {step * height} bytes ({height} rows of step {step}), its data "
                          f"has {len(image.data)}")
    rows = np.frombuffer(image.data, np.uint8, count=step * height).reshape(height, step)
    return rows[:, :row].reshape(height, width, layout.bytes_per_pixel)


def samples_format(image: Any) -> str:
    """FFmpeg's name for ``image``'s samples as they are (a mosaic's as grey), 16-bit ones in their byte order
    (``is_bigendian``): what a PNG of them reads."""
    name = format_of(image).samples_format
    return name.replace("le", "be") if name.endswith("16le") and image.is_bigendian else name


#: Formats an FFmpeg frame can wrap in the message's own buffer (PyAV's from_numpy_buffer), no copy.
WRAPPED = {"rgb24": 3, "bgr24": 3, "rgba": 4, "bgra": 4}
#: RGB formats whose conversion to 4:2:0 at the same size point-samples the chroma: 1.7 ms less per 1080p frame
#: than bilinear averaging, at the same PSNR once encoded (S4's measurements, CHANGELOG.md).
POINT_SAMPLED = frozenset(WRAPPED)


def frame_of(pixels: np.ndarray, av_format: str) -> VideoFrame:
    """An FFmpeg frame of ``av_format`` holding ``pixels`` ((height, width, bytes per pixel)): the message's
    own buffer where FFmpeg can read it as it is (:data:`WRAPPED`), else one copy into a buffer FFmpeg allocated
    (aligned and padded, as swscale and the encoders read it)."""
    if WRAPPED.get(av_format) == pixels.shape[2] and pixels.strides[1:] == (pixels.shape[2], 1):
        return av().VideoFrame.from_numpy_buffer(pixels, format=av_format)
    height, width, depth = pixels.shape
    frame = av().VideoFrame(width, height, av_format)
    plane = frame.planes[0]
    target = np.frombuffer(plane, np.uint8).reshape(height, plane.line_size)
    target[:, :width * depth] = pixels.reshape(height, width * depth)
    return frame


def converted(pixels: np.ndarray, av_format: str, size: tuple[int, int], target: str, **swscale: Any) -> VideoFrame:
    """``pixels`` (of ``av_format``) as an FFmpeg frame of ``target`` at ``size``, converted and scaled by swscale
    on the calling thread (``swscale``: reformat's options, e.g. colour ranges; swscale's own threads started a
    pool per frame); the frame itself when nothing changes.

    Bayer is demosaiced to RGB first, at its own size: swscale's direct paths from Bayer (to YUV, or scaled) get
    the colours wrong (17 dB PSNR against its own demosaic to RGB, measured on a 256x192 gradient).
    """
    frame = frame_of(pixels, av_format)
    if av_format.startswith("bayer_"):
        frame = frame.reformat(format="rgb24", threads=1)
    if av_format in POINT_SAMPLED and target == "yuv420p" and (frame.width, frame.height) == size:
        swscale.setdefault("interpolation", "POINT")
    return frame.reformat(width=size[0], height=size[1], format=target, threads=1, **swscale)


def plane_view(frame: VideoFrame, index: int = 0, bytes_per_pixel: int = 1) -> np.ndarray:
    """Plane ``index`` of ``frame`` as a (height, width, bytes per pixel) view without its row padding (strides
    given outright: a side of one pixel still has contiguous rows, as simplejpeg checks)."""
    plane = frame.planes[index]
    return np.ndarray((plane.height, plane.width, bytes_per_pixel), np.uint8, buffer=plane,
                      strides=(plane.line_size, bytes_per_pixel, 1))
