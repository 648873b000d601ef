"""The codecs behind ``components::ImageEncoder``: libjpeg-turbo (simplejpeg) for JPEG, FFmpeg (PyAV) for the rest.

No codec or bitstream parser is written here. A :class:`Codec` turns one ``sensor_msgs/Image``'s pixels (a numpy
view of the message's own buffer, never a copy) into the bytes of one message:

* stills (``jpeg``, ``png``): one self-contained picture per frame, for ``sensor_msgs/CompressedImage``, with the
  ``format`` string that image_transport's ``compressed`` publisher writes (``"rgb8; jpeg compressed bgr8"``);
* video (``h264``, ``h265``, ``av1`` or an FFmpeg encoder name such as ``h264_nvenc``): one access unit per frame
  (Annex B for H.264/H.265, low-overhead OBUs for AV1), no B-frames and no look-ahead so that each frame comes
  out as soon as it goes in, keyframes with their parameter sets every ``keyframe_interval`` frames and on
  request (:meth:`VideoCodec.encode` with ``keyframe=True``), for ``foxglove_msgs/CompressedVideo``.

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
from components.image_encoder._pyav import av
from components.image_encoder.scheduling import ordinary_scheduling, without_sys_nice

if TYPE_CHECKING:
    from av import VideoFrame

#: The short names of the video formats CompressedVideo carries, and the FFmpeg encoder each one means.
VIDEO_ENCODERS = {"h264": "libx264", "h265": "libx265", "av1": "libsvtav1"}
#: FFmpeg's codec name -> CompressedVideo ``format`` (an encoder named directly, e.g. ``hevc_nvenc``).
VIDEO_FORMATS = {"h264": "h264", "hevc": "h265", "av1": "av1"}
STILLS = ("jpeg", "png")
#: Quality ranges by codec: JPEG quality, PNG compression level, CRF of x264 / x265 / SVT-AV1.
QUALITY = {"jpeg": Bounds(1, 100), "png": Bounds(0, 9), "h264": Bounds(0, 51), "h265": Bounds(0, 51),
           "av1": Bounds(1, 63)}
#: Defaults where ``quality`` is not given (-1).
DEFAULT_QUALITY = {"jpeg": 90, "png": 3, "h264": 23, "h265": 28, "av1": 35}
#: Defaults where ``preset`` is not given (""): fast enough for 1080p30 on one core of a small machine; for x264
#: the cheapest per frame at the benchmark's quality and size targets (ultrafast: 1.7x fewer CPU ms per 1080p photo
#: frame than veryfast, at a higher PSNR and 0.2 % of the raw bytes; CHANGELOG.md, S4's codec limits).
DEFAULT_PRESET = {"libx264": "ultrafast", "libx265": "ultrafast", "libsvtav1": "10"}
#: x264 encodes pictures up to this size on the calling thread alone (one thread per camera): its own threads cost
#: 4-10 % more CPU per 1080p frame, and several cameras keep every core busy anyway. Larger pictures (4K) get
#: x264's threads, without which one camera's frame no longer fits a frame interval at 30 Hz.
ONE_THREAD_PIXELS = 2560 * 1440
#: sensor_msgs encodings the encoder takes: numpy channels, simplejpeg colourspace, PyAV pixel format.
PIXELS = {"rgb8": (3, "RGB", "rgb24"), "bgr8": (3, "BGR", "bgr24"), "rgba8": (4, "RGBA", "rgba"),
          "bgra8": (4, "BGRA", "bgra"), "mono8": (1, "GRAY", "gray")}
#: Time base of the pts handed to the encoder: frame numbers at a nominal 30 Hz (rate control only).
TIME_BASE = fractions.Fraction(1, 30)


@dataclass(frozen=True)
class CodecChoice:
    """What the parameters chose: the message kind, the encoder and its settings."""

    codec: str          # as given: "jpeg", "png", "h264", ... or an FFmpeg encoder name
    encoder: str        # the FFmpeg encoder ("libx264"), or "simplejpeg" for JPEG
    video_format: str   # CompressedVideo.format ("h264", "h265", "av1"); "" for stills
    preset: str
    quality: int        # -1: bitrate rules (video only)
    bitrate: int        # bits/s, 0: quality rules
    keyframe_interval: int

    @property
    def is_video(self) -> bool:
        return bool(self.video_format)


class EncodeError(ValueError):
    """A frame this codec cannot take (its encoding or size); the frame is counted as rejected."""


def choose(codec: str, preset: str, quality: int, bitrate: int, keyframe_interval: int,
           prefix: str = "") -> CodecChoice:
    """Resolve and check the codec parameters; ValueError naming the parameter at fault (``prefix`` + name:
    the Foxglove bridge's are ``video.codec``, ...)."""
    if codec in STILLS:
        if bitrate:
            raise ValueError(f"parameter '{prefix}bitrate' applies to video codecs only, not to {codec!r}")
        encoder, video_format = ("simplejpeg" if codec == "jpeg" else "png"), ""
    else:
        encoder = VIDEO_ENCODERS.get(codec, codec)
        try:
            found = av().Codec(encoder, "w")
        except Exception:  # PyAV raises UnknownCodecError (and others for odd names)
            raise ValueError(f"parameter '{prefix}codec': {codec!r} is neither jpeg, png, {', '.join(VIDEO_ENCODERS)} "
                             "nor an FFmpeg video encoder this installation has") from None
        video_format = VIDEO_FORMATS.get(found.canonical_name, "")
        if found.type != "video" or not video_format:
            raise ValueError(f"parameter '{prefix}codec': encoder {encoder!r} writes {found.canonical_name}, which "
                             f"foxglove_msgs/CompressedVideo cannot carry (it takes {', '.join(VIDEO_FORMATS)})")
    kind = codec if codec in QUALITY else video_format
    if quality != -1:
        QUALITY[kind].check(f"'{prefix}quality' ({'CRF' if video_format else codec})", quality)
    elif not bitrate:
        quality = DEFAULT_QUALITY[kind]
    if quality != -1 and bitrate:
        raise ValueError(f"parameters '{prefix}quality' and '{prefix}bitrate': give one of them, not both")
    return CodecChoice(codec, encoder, video_format, preset or DEFAULT_PRESET.get(encoder, ""), quality, bitrate,
                       keyframe_interval)


def check_codec(choice: CodecChoice, prefix: str = "") -> None:
    """Open the encoder once on a small picture: what the machine lacks fails here, at load, naming ``codec``."""
    if not choice.is_video:
        return
    try:
        VideoCodec(choice, 64, 64).close()
    except Exception as exc:  # FFmpeg's errors for a missing device, a bad preset, an option it refuses
        raise ValueError(f"parameter '{prefix}codec' (or '{prefix}preset' {choice.preset!r}): encoder "
                         f"{choice.encoder!r} cannot be opened on this machine: {exc}") from None


def pixels_of(image: Any) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` as a (height, width[, channels]) view of its own data buffer."""
    layout = PIXELS.get(image.encoding)
    if layout is None:
        raise EncodeError(f"encoding {image.encoding!r} is not supported (only {', '.join(PIXELS)})")
    channels = layout[0]
    height, width, step = image.height, image.width, image.step
    if step < width * channels or len(image.data) < step * height:
        raise EncodeError(f"a {width}x{height} {image.encoding} image needs {width * channels * height} bytes in "
                          f"rows of step {step}, it has {len(image.data)}")
    rows = np.frombuffer(image.data, np.uint8, count=step * height).reshape(height, step)
    view = rows[:, :width * channels]
    return view if channels == 1 else view.reshape(height, width, channels)


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


def _frame(pixels: np.ndarray, encoding: str, size: tuple[int, int], pix_fmt: str) -> VideoFrame:
    """An FFmpeg frame of ``pixels`` (wrapping the message's buffer: no copy) converted (swscale, on the calling
    thread) to ``size`` and ``pix_fmt``. At the same size the conversion scales nothing but the chroma of 4:2:0,
    which point sampling takes for 1.7 ms less per 1080p frame than bilinear averaging, at the same PSNR once
    encoded (S4's measurements, CHANGELOG.md)."""
    frame = av().VideoFrame.from_numpy_buffer(pixels, format=PIXELS[encoding][2])
    if (frame.width, frame.height) == size and frame.format.name == pix_fmt:
        return frame
    return frame.reformat(width=size[0], height=size[1], format=pix_fmt, threads=1,
                          interpolation="POINT" if (frame.width, frame.height) == size else None)


class StillCodec:
    """JPEG (libjpeg-turbo, 4:2:0) or PNG (FFmpeg) pictures with image_transport's ``format`` strings."""

    def __init__(self, choice: CodecChoice, out_width: int) -> None:
        self._choice = choice
        self._out_width = out_width
        self._png: dict[tuple[int, int, str], Any] = {}

    def format_of(self, encoding: str) -> str:
        """``format`` as compressed_image_transport writes it: colour 8-bit images are stored as bgr8 (PNG:
        bgra8 with alpha); grey JPEG is mono8, grey PNG names no target."""
        colour = PIXELS[encoding][0] > 1
        if self._choice.codec == "jpeg":
            return f"{encoding}; jpeg compressed {'bgr8' if colour else 'mono8'}"
        target = ("bgra8" if PIXELS[encoding][0] == 4 else "bgr8") if colour else ""
        return f"{encoding}; png compressed {target}"

    def encode(self, image: Any) -> bytes:
        pixels = pixels_of(image)
        size = scaled_size(image.width, image.height, self._out_width, even=False)
        if self._choice.codec == "jpeg":
            if size != (image.width, image.height):
                pixels = _frame(pixels, image.encoding, size, PIXELS[image.encoding][2]).to_ndarray()
            return simplejpeg.encode_jpeg(pixels, self._choice.quality, PIXELS[image.encoding][1], "420")
        pix_fmt = PIXELS[image.encoding][2]
        key = (*size, pix_fmt)
        context = self._png.get(key)
        if context is None:
            context = self._png[key] = av().CodecContext.create("png", "w")
            context.width, context.height, context.pix_fmt = size[0], size[1], pix_fmt
            context.options = {"compression_level": str(self._choice.quality)}
        return b"".join(bytes(p) for p in context.encode(_frame(pixels, image.encoding, size, pix_fmt)))

    def close(self) -> None:
        self._png.clear()


class VideoCodec:
    """One FFmpeg video encoder of a fixed size: frames in, one access unit out per frame."""

    def __init__(self, choice: CodecChoice, width: int, height: int) -> None:
        self.size = (width, height)
        context = av().CodecContext.create(choice.encoder, "w")
        context.width, context.height, context.pix_fmt = width, height, "yuv420p"
        context.time_base, context.framerate = TIME_BASE, 1 / TIME_BASE
        context.gop_size = choice.keyframe_interval
        context.max_b_frames = 0
        options = _encoder_options(choice, width * height)
        if choice.bitrate:
            context.bit_rate = choice.bitrate
        context.options = options
        with ordinary_scheduling():  # SVT-AV1 as root makes threads real-time
            context.open()
        self._context = context
        self._pts = 0

    @property
    def next_pts(self) -> int:
        """The pts the next frame gets (frame numbers): the caller maps it to the frame's stamp."""
        return self._pts

    def encode(self, pixels: np.ndarray, encoding: str, keyframe: bool) -> list[tuple[int, bool, bytes]]:
        """Encode one frame; the ``(pts, keyframe, access unit)`` the encoder gave out (normally just this one)."""
        frame = _frame(pixels, encoding, self.size, "yuv420p")
        frame.pts, self._pts = self._pts, self._pts + 1
        if keyframe:
            frame.pict_type = av().video.frame.PictureType.I
        with without_sys_nice():  # SVT-AV1 starts threads while encoding too: never real-time ones
            packets = self._context.encode(frame)
        return [(p.pts, p.is_keyframe, bytes(p)) for p in packets]

    def close(self) -> None:
        self._context = None


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
        options["svtav1-params"] = "pred-struct=1:lookahead=0:scd=0"  # low delay: one frame in, one out
    if choice.encoder == "libx264" and pixels <= ONE_THREAD_PIXELS:
        options["threads"] = "1"
    if choice.quality != -1 and choice.encoder in ("libx264", "libx265", "libsvtav1"):
        options["crf"] = str(choice.quality)
    elif choice.quality != -1:
        options["qp"] = str(choice.quality)  # hardware encoders: a constant quantiser
    return options
