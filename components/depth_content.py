"""Depth frames for the simulated camera: ``content:=photo`` in ``16UC1`` or ``mono16`` shows a range image.

Why: what a depth codec does with a depth camera's frames cannot be measured on random 16-bit values (noise no
lossless codec compresses) nor on the photograph (a colour picture is no range image). A depth camera sees
surfaces: smooth ranges that change slowly across the picture and jump at edges.

The scene, in millimetres along the optical axis (what ``16UC1`` depth holds), for a camera 0.8 m above a floor
and 1.9 m below a ceiling, facing a wall 2.5 ... 5.5 m away whose distance rises and falls along its length, with
round pillars standing between; the rows below and above the horizon meet the floor and the ceiling where they are
nearer than the wall. It is computed once per process and camera size with numpy (:func:`panorama`), as one wide
range image that repeats after :data:`PANORAMA_FRAMES` frames of pan; frame ``n`` is the camera-wide window at
column ``n * PAN_PIXELS_PER_FRAME`` of it (the first columns are repeated at the right for the wrap-around), one
copy into the frame buffer: a function of ``n`` alone, as components/frame_buffers.py requires.
"""
from __future__ import annotations

import functools
import math

import numpy as np

#: Columns the window moves per frame (as the photo content's pan).
PAN_PIXELS_PER_FRAME = 6
#: Frames until the pan comes round to the start: the panorama is this many pans wide.
PANORAMA_FRAMES = 1024
#: The camera's horizontal field of view (as components/camera_driver.py's CameraInfo).
HORIZONTAL_FOV_DEG = 60.0
#: Heights in metres of the camera above the floor and of the ceiling above the camera.
FLOOR_M, CEILING_M = 0.8, 1.9
#: The wall's distance: mean and amplitude in metres, and its waves over one panorama.
WALL_M, WALL_SWING_M, WALL_WAVES = 4.0, 1.5, (3, 7)
#: Pillars: how many along one panorama, their radius and their distance in metres.
PILLARS, PILLAR_RADIUS_M, PILLAR_M = 5, 0.3, 2.0


@functools.lru_cache(maxsize=None)
def panorama(width: int, height: int) -> np.ndarray:
    """The read-only (height, panorama columns + width) uint16 range image, in millimetres; shared by every depth
    camera of this size in the process."""
    focal = width / (2.0 * math.tan(math.radians(HORIZONTAL_FOV_DEG) / 2.0))
    columns = PANORAMA_FRAMES * PAN_PIXELS_PER_FRAME
    along = np.arange(columns) / columns * 2 * math.pi  # one turn of every periodic feature per panorama
    wall = WALL_M + WALL_SWING_M * 0.5 * (np.sin(WALL_WAVES[0] * along) + np.sin(WALL_WAVES[1] * along + 1.0))
    # A pillar's front surface: nearest at its axis, rounding off over its radius (seen from PILLAR_M away).
    spacing = columns / PILLARS
    offset = (np.arange(columns) % spacing - spacing / 2) * PILLAR_M / focal  # metres from the nearest axis
    pillar = np.where(np.abs(offset) < PILLAR_RADIUS_M,
                      PILLAR_M - np.sqrt(np.maximum(PILLAR_RADIUS_M ** 2 - offset ** 2, 0.0)) + PILLAR_RADIUS_M,
                      np.inf)
    ahead = np.minimum(wall, pillar)[None, :]
    # Rows below the horizon meet the floor at FLOOR_M * focal / rows-below; above it, the ceiling likewise.
    below = (np.arange(height) - (height - 1) / 2.0)[:, None]
    plane = np.where(below > 0, FLOOR_M, CEILING_M) * focal / np.maximum(np.abs(below), 1e-9)
    metres = np.minimum(ahead, plane)
    image = np.rint(metres * 1000.0).astype(np.uint16)
    wrapped = np.concatenate([image, image[:, :width]], axis=1)
    wrapped.setflags(write=False)
    return wrapped


class DepthContent:
    """Fills frame buffers of one depth camera with windows of the range image (module docstring)."""

    def __init__(self, width: int, height: int) -> None:
        self.width, self.height = width, height
        self.panorama = panorama(width, height)

    def column_of(self, sequence: int) -> int:
        """The panorama column where frame ``sequence`` begins."""
        return sequence * PAN_PIXELS_PER_FRAME % (PANORAMA_FRAMES * PAN_PIXELS_PER_FRAME)

    def fill(self, sequence: int, buffer: memoryview) -> None:
        """Write frame ``sequence`` into ``buffer`` (``width * height`` native-order uint16 samples)."""
        column = self.column_of(sequence)
        target = np.frombuffer(buffer, dtype=np.uint16).reshape(self.height, self.width)
        np.copyto(target, self.panorama[:, column:column + self.width])
