"""The codecs behind ``components::ImageEncoder``: libjpeg-turbo (simplejpeg) for JPEG, FFmpeg (PyAV) for the rest.

No codec, colour conversion or bitstream parser is written here. A :class:`Codec` turns one ``sensor_msgs/Image``'s
pixels (a numpy view of the message's own buffer) into the bytes of one message:

* stills (``jpeg``, ``png``): one self-contained picture per frame, for ``sensor_msgs/CompressedImage``, with the
  ``format`` string that image_transport's ``compressed`` publisher writes (``"rgb8; jpeg compressed bgr8"``);
  ``compressedDepth``: 16-bit depth as image_transport's ``compressedDepth`` transport has it (compressed_depth.py);
* video (``h264``, ``h265``, ``av1`` or an FFmpeg encoder name such as ``h264_nvenc``): one access unit per frame
  (Annex B for H.264/H.265, low-overhead OBUs for AV1), no B-frames and no look-ahead so that each frame comes
  out as soon as it goes in, keyframes with their parameter sets every ``keyframe_interval`` frames and on
  request (:meth:`VideoCodec.encode` with ``keyframe=True``), for ``foxglove_msgs/CompressedVideo``.

The pixels go to a codec as the camera gave them, converted by FFmpeg's swscale only into what that codec takes
(pixel_formats.py): video is 4:2:0, made straight from YUV 4:2:2 or Bayer as from RGB; JPEG gets RGB, grey, or
(YUV 4:2:2) 4:2:0 planes; PNG gets RGB, grey or 16-bit grey.

Every choice is checked when the component loads, by opening the encoder once on a small picture
(:func:`check_codec`): an encoder the machine lacks or a preset it does not know is a load error naming the
parameter, not a failure at the first frame.
"""
from __future__ import annotations

import fractions
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import simplejpeg

from components.bounds import Bounds
from components.image_encoder import compressed_depth
from components.image_encoder._pyav import av
from components.image_encoder.pixel_formats import (FORMATS, EncodeError, PixelFormat, converted, describe, format_of,
                                                    pixels_of, plane_view, samples_format)
from components.image_encoder.scheduling import ordinary_scheduling

if TYPE_CHECKING:
    from av.codec.context import CodecContext

#: The short names of the video formats CompressedVideo carries, and the FFmpeg encoder each one means.
VIDEO_ENCODERS = {"h264": "libx264", "h265": "libx265", "av1": "libsvtav1"}
#: FFmpeg's codec name -> CompressedVideo ``format`` (an encoder named directly, e.g. ``hevc_nvenc``).
VIDEO_FORMATS = {"h264": "h264", "hevc": "h265", "av1": "av1"}
#: 16-bit depth in image_transport's compressedDepth format (a PNG after its header), on ``<image>/compressedDepth``.
#: Parameters are read in lower case: ``codec:=compressedDepth`` names it.
DEPTH = "compresseddepth"
STILLS = ("jpeg", "png", DEPTH)
#: Quality ranges by codec: JPEG quality, PNG compression level, CRF of x264 / x265 / SVT-AV1.
QUALITY = {"jpeg": Bounds(1, 100), "png": Bounds(0, 9), DEPTH: Bounds(0, 9), "h264": Bounds(0, 51),
           "h265": Bounds(0, 51), "av1": Bounds(1, 63)}
#: Defaults where ``quality`` is not given (-1). compressedDepth: PNG's level 3 too (upstream's publisher uses 9,
#: three times the CPU of 3 for a 1080p range image).
DEFAULT_QUALITY = {"jpeg": 90, "png": 3, DEPTH: 3, "h264": 23, "h265": 28, "av1": 35}
#: Defaults where ``preset`` is not given (""): fast enough for 1080p30 on one core of a small machine; for x264
#: the cheapest per frame at the benchmark's quality and size targets (ultrafast: 1.7x fewer CPU ms per 1080p photo
#: frame than veryfast, at a higher PSNR and 0.2 % of the raw bytes; CHANGELOG.md, S4's codec limits).
DEFAULT_PRESET = {"libx264": "ultrafast", "libx265": "ultrafast", "libsvtav1": "11"}
#: SVT-AV1's fastest preset that runs in its real-time mode (``rtc=1``, which the encoder uses) without stopping
#: for good now and then; faster ones are refused (preset 12 stops like the non-real-time low-delay mode did:
#: docs/image-encoder.md, "AV1's real-time mode").
SVT_AV1_FASTEST = 11
#: x264 encodes pictures up to this size on the calling thread alone (one thread per camera): its own threads cost
#: 4-10 % more CPU per 1080p frame, and several cameras keep every core busy anyway. Larger pictures (4K) get
#: x264's threads, without which one camera's frame no longer fits a frame interval at 30 Hz.
ONE_THREAD_PIXELS = 2560 * 1440
#: simplejpeg's colourspace, and bytes per pixel, of the FFmpeg pixel formats it encodes as they are.
JPEG_INPUTS = {"rgb24": ("RGB", 3), "bgr24": ("BGR", 3), "rgba": ("RGBA", 4), "bgra": ("BGRA", 4), "gray": ("GRAY", 1)}
#: Time base of the pts handed to the encoder: frame numbers at a nominal 30 Hz (rate control only).
TIME_BASE = fractions.Fraction(1, 30)


@dataclass(frozen=True)
class CodecChoice:
    """What the parameters chose: the message kind, the encoder and its settings."""

    codec: str          # as given: "jpeg", "png", "compresseddepth", "h264", ... or an FFmpeg encoder name
    encoder: str        # the FFmpeg encoder ("libx264", "png"), or "simplejpeg" for JPEG
    video_format: str   # CompressedVideo.format ("h264", "h265", "av1"); "" for stills
    preset: str
    quality: int        # -1: bitrate rules (video only)
    bitrate: int        # bits/s, 0: quality rules
    keyframe_interval: int

    @property
    def is_video(self) -> bool:
        return bool(self.video_format)

    @property
    def transport(self) -> str:
        """The last name part of the output topic, known from the parameters before any frame: image_transport's
        ``compressed`` or ``compressedDepth``, or this project's ``video``."""
        if self.is_video:
            return "video"
        return compressed_depth.TRANSPORT if self.codec == DEPTH else "compressed"


def choose(codec: str, preset: str, quality: int, bitrate: int, keyframe_interval: int,
           prefix: str = "") -> CodecChoice:
    """Resolve and check the codec parameters; ValueError naming the parameter at fault (``prefix`` + name:
    the Foxglove bridge's are ``video.codec``, ...)."""
    codec = codec.strip().lower()
    if codec in STILLS:
        if bitrate:
            raise ValueError(f"parameter '{prefix}bitrate' applies to video codecs only, not to {codec!r}")
        encoder, video_format = ("simplejpeg" if codec == "jpeg" else "png"), ""
    else:
        encoder = VIDEO_ENCODERS.get(codec, codec)
        try:
            found = av().Codec(encoder, "w")
        except Exception:  # PyAV raises UnknownCodecError (and others for odd names)
            raise ValueError(f"parameter '{prefix}codec': {codec!r} is neither jpeg, png, compressedDepth, "
                             f"{', '.join(VIDEO_ENCODERS)} nor an FFmpeg video encoder this installation has") from None
        video_format = VIDEO_FORMATS.get(found.canonical_name, "")
        if found.type != "video" or not video_format:
            raise ValueError(f"parameter '{prefix}codec': encoder {encoder!r} writes {found.canonical_name}, which "
                             f"foxglove_msgs/CompressedVideo cannot carry (it takes {', '.join(VIDEO_FORMATS)})")
    kind = codec if codec in QUALITY else video_format
    if quality != -1:
        meaning = "CRF" if video_format else "JPEG quality" if codec == "jpeg" else "PNG compression level"
        QUALITY[kind].check(f"'{prefix}quality' ({meaning})", quality)
    elif not bitrate:
        quality = DEFAULT_QUALITY[kind]
    if quality != -1 and bitrate:
        raise ValueError(f"parameters '{prefix}quality' and '{prefix}bitrate': give one of them, not both")
    preset = preset or DEFAULT_PRESET.get(encoder, "")
    if encoder == "libsvtav1" and preset.isdigit() and int(preset) > SVT_AV1_FASTEST:
        raise ValueError(f"parameter '{prefix}preset': SVT-AV1's preset {preset} stops for good now and then in its "
                         f"real-time mode, which the av1 encoder runs: take {SVT_AV1_FASTEST} or a lower one")
    return CodecChoice(codec, encoder, video_format, preset, quality, bitrate, keyframe_interval)


def check_codec(choice: CodecChoice, prefix: str = "") -> None:
    """Open the encoder once on a small picture: what the machine lacks fails here, at load, naming ``codec``
    (and ``preset`` where one applies: a hardware encoder has none unless given)."""
    if not choice.is_video:
        return
    try:
        _open_video(choice, 64, 64)
    except Exception as exc:  # FFmpeg's errors for a missing device, a bad preset, an option it refuses
        named = f"'{prefix}codec'" + (f" (or its '{prefix}preset' {choice.preset!r})" if choice.preset else "")
        raise ValueError(f"parameter {named}: encoder {choice.encoder!r} cannot be opened on this machine: "
                         f"{exc}") from None


def scaled_size(width: int, height: int, out_width: int, even: bool, at_most: bool = False) -> tuple[int, int]:
    """The output size for ``out_width`` (0: the input's), keeping the aspect ratio; even sides for 4:2:0.

    ``at_most``: ``out_width`` is a maximum (a viewer's), so a narrower image keeps its width, and an odd side
    is rounded to even rather than refused.
    """
    if at_most:
        out_width = min(out_width or width, width)
        out_width -= out_width % 2 if even else 0
        if out_width == width and not (even and height % 2):
            return width, height
    elif not out_width or out_width == width:
        if even and (width % 2 or height % 2):
            raise EncodeError(f"a {width}x{height} image has an odd side, which 4:2:0 video cannot hold; "
                              "set 'width' to an even output width")
        return width, height
    out_height = max(1, round(height * out_width / width))
    return out_width, out_height + (out_height % 2 if even else 0)


class StillCodec:
    """JPEG (libjpeg-turbo, 4:2:0), PNG or compressedDepth (FFmpeg's PNG) pictures with image_transport's
    ``format`` strings."""

    def __init__(self, choice: CodecChoice, out_width: int) -> None:
        self._choice = choice
        self._out_width = out_width
        self._png: dict[tuple[int, int, str], CodecContext] = {}

    def format_of(self, encoding: str) -> str:
        """``format`` as image_transport's publishers write it: ``"<encoding>; jpeg compressed bgr8"``,
        ``"<encoding>; png compressed bgr8"`` (bgra8 with alpha, no target for grey, as upstream), and
        ``"<encoding>; compressedDepth png"``. A still whose colours FFmpeg made (of YUV, or a JPEG of Bayer) is
        named ``rgb8``: the encoding its decoder gives back (image_transport's subscribers read the name so)."""
        if self._choice.codec == DEPTH:
            return compressed_depth.format_string(encoding)
        layout = FORMATS[encoding]
        if self._choice.codec == "jpeg":
            named = layout.converted_as or encoding
            return f"{named}; jpeg compressed {'mono8' if layout.jpeg_input == 'gray' else 'bgr8'}"
        named = encoding if layout.is_mosaic else layout.converted_as or encoding
        stored = layout.png_format
        return f"{named}; png compressed {'' if stored.startswith('gray') else 'bgra8' if stored == 'rgba' else 'bgr8'}"

    def encode(self, image: Any) -> bytes:
        pixels = pixels_of(image)
        layout = format_of(image)
        size = scaled_size(image.width, image.height, self._out_width, even=False)
        if self._choice.codec == "jpeg":
            return self._jpeg(image, layout, pixels, size)
        if self._choice.codec == DEPTH and not layout.is_depth:
            raise EncodeError(f"{describe(image)} is not 16-bit depth: compressedDepth takes 16UC1 and mono16 "
                              "(encode other images with jpeg, png or a video codec)")
        if layout.is_mosaic and size != (image.width, image.height):
            raise EncodeError(f"{describe(image)}: PNG keeps a Bayer mosaic as it is (lossless), and a mosaic "
                              "cannot be scaled to 'width'; scale with jpeg or a video codec, which demosaic it")
        target = layout.png_format
        # Depth scaled to 'width' keeps measured values only (nearest sample), never a blend of near and far.
        frame = converted(pixels, samples_format(image), size, target,
                          **({"interpolation": "POINT"} if layout.is_depth else {}))
        key = (*size, target)
        context = self._png.get(key)
        if context is None:
            context = self._png[key] = av().CodecContext.create("png", "w")
            context.width, context.height, context.pix_fmt = size[0], size[1], target
            context.options = {"compression_level": str(self._choice.quality)}
        header = [compressed_depth.header()] if self._choice.codec == DEPTH else []
        return b"".join([*header, *(bytes(p) for p in context.encode(frame))])

    def _jpeg(self, image: Any, layout: PixelFormat, pixels: np.ndarray, size: tuple[int, int]) -> bytes:
        quality = self._choice.quality
        if not layout.jpeg_input:
            raise EncodeError(f"{describe(image)} holds 16-bit samples, which JPEG cannot: encode it with codec "
                              "png or compressedDepth (both lossless)")
        if layout.jpeg_input == "yuv420p":  # YUV 4:2:2: its planes at 4:2:0, in the full range JPEG has them
            frame = converted(pixels, layout.av_format, size, "yuv420p", src_color_range="MPEG",
                              dst_color_range="JPEG")
            return simplejpeg.encode_jpeg_yuv_planes(*(plane_view(frame, i)[:, :, 0] for i in range(3)), quality)
        colourspace, bytes_per_pixel = JPEG_INPUTS[layout.jpeg_input]
        if layout.jpeg_input != layout.av_format or size != (image.width, image.height):
            pixels = plane_view(converted(pixels, layout.av_format, size, layout.jpeg_input), 0, bytes_per_pixel)
        return simplejpeg.encode_jpeg(pixels, quality, colourspace, "420")

    def close(self) -> None:
        self._png.clear()


class VideoCodec:
    """One FFmpeg video encoder of a fixed size: frames in, one access unit out per frame."""

    def __init__(self, choice: CodecChoice, width: int, height: int) -> None:
        self.size = (width, height)
        try:
            self._context: CodecContext | None = _open_video(choice, width, height)
        except av().FFmpegError as exc:
            raise EncodeError(f"a {width}x{height} frame: encoder {choice.encoder!r} cannot be opened for this size "
                              f"({exc})") from None
        self._pts = 0

    @property
    def next_pts(self) -> int:
        """The pts the next frame gets (frame numbers): the caller maps it to the frame's stamp."""
        return self._pts

    def encode(self, pixels: np.ndarray, encoding: str, keyframe: bool) -> list[tuple[int, bool, bytes]]:
        """Encode one frame (``pixels``: :func:`pixels_of`'s view); the ``(pts, keyframe, access unit)`` the
        encoder gave out (normally just this one)."""
        layout = FORMATS[encoding]
        if layout.is_depth:
            raise EncodeError(f"a {pixels.shape[1]}x{pixels.shape[0]} {encoding} image holds 16-bit depth, which "
                              "8-bit 4:2:0 video cannot: encode it with codec png or compressedDepth (lossless)")
        frame = converted(pixels, layout.av_format, self.size, "yuv420p")
        frame.pts, self._pts = self._pts, self._pts + 1
        if keyframe:
            frame.pict_type = av().video.frame.PictureType.I
        assert self._context is not None, "encode after close"
        packets = self._context.encode(frame)
        return [(p.pts, p.is_keyframe, bytes(p)) for p in packets]

    def close(self) -> None:
        self._context = None


def _open_video(choice: CodecChoice, width: int, height: int) -> CodecContext:
    """The chosen encoder opened for ``width`` x ``height`` 4:2:0 frames; FFmpeg's error where it cannot be."""
    context = av().CodecContext.create(choice.encoder, "w")
    context.width, context.height, context.pix_fmt = width, height, "yuv420p"
    context.time_base, context.framerate = TIME_BASE, 1 / TIME_BASE
    context.gop_size = choice.keyframe_interval
    context.max_b_frames = 0
    if choice.bitrate:
        context.bit_rate = choice.bitrate
    context.options = _encoder_options(choice, width * height)
    with ordinary_scheduling():  # SVT-AV1 as root makes threads real-time; it starts them all here
        context.open()
    return context


def _encoder_options(choice: CodecChoice, pixels: int) -> dict[str, str]:
    """FFmpeg options for low delay (no look-ahead, forced keyframes are IDR), x264's threads for pictures of
    ``pixels`` (:data:`ONE_THREAD_PIXELS`) and the chosen rate control."""
    options: dict[str, str] = {}
    if choice.preset:
        options["preset"] = choice.preset
    if choice.encoder in ("libx264", "libx265"):
        options.update({"tune": "zerolatency", "forced-idr": "1"})
        if choice.encoder == "libx265":
            options["x265-params"] = "log-level=error"
    elif choice.encoder == "libsvtav1":
        # SVT-AV1's real-time mode: low-delay prediction, one frame in, one out. Its other low-delay path
        # (pred-struct=1 without rtc) stops for good now and then, every thread waiting on another.
        options["svtav1-params"] = "rtc=1"
    if choice.encoder == "libx264" and pixels <= ONE_THREAD_PIXELS:
        options["threads"] = "1"
    if choice.quality != -1 and choice.encoder in ("libx264", "libx265", "libsvtav1"):
        options["crf"] = str(choice.quality)
    elif choice.quality != -1:
        options["qp"] = str(choice.quality)  # hardware encoders: a constant quantiser
    return options
