"""Simulated spinning lidar: publishes ``sensor_msgs/PointCloud2`` scans at ``rate``.

Parameters (validated at construction; a bad value raises ValueError naming the parameter and its range).
``rate`` and ``frame_id`` can be changed at run time (``ros2 param set``); the others are read-only:

===================  ============  ==========================================================================
``points_per_scan``  32768         points per cloud (1 ... 2796202, a 64 MiB scan); benchmarks use 131072
``rings``            32            laser rings (1 ... 1024, at most points_per_scan)
``rate``             10.0          scans per second (0.01 ... 2000, at most 1 GB/s of scans)
``frame_id``         ``'lidar'``   header.frame_id
``topic``            ``'~/points'``
``qos``              ``'reliable'``  ``'reliable'`` or ``'sensor_data'`` (best effort)
===================  ============  ==========================================================================

Point layout (like Velodyne/Ouster ``PointXYZIRT`` drivers), little-endian, ``point_step`` 24, ``height`` 1,
``width`` = points_per_scan, ``row_step`` = 24 * width, ``is_dense`` true:

=============  ======  ========  ==========================================================
``x``          0       float32   metres
``y``          4       float32
``z``          8       float32
``intensity``  12      float32   0 ... 255
``ring``       16      uint16    0 = lowest beam; bytes 18-19 are padding
``time``       20      float32   seconds after header.stamp (start of the sweep), [0, 1/rate)
=============  ======  ========  ==========================================================

Points are ordered column by column (all rings of one azimuth, then the next azimuth), as the sensor fires.
The scene is a 40 m x 28 m walled room with a floor and a ceiling, seen from 1.8 m above the floor with a 30
degree vertical field of view.

Generation: the noise-free scan is packed once into an immutable ``bytes`` template, and a pool of Gaussian
position noise (sigma 1 cm, one scan's worth plus three strides of points) is drawn once. Scan ``n`` is the
template plus the noise slice at offset ``(n % FRAME_SLOTS) * OFFSET_STRIDE`` (so consecutive scans differ):
one memcpy of the template into a fresh ``array.array('B')`` plus one strided numpy add into that buffer
(numpy only views it and is never assigned to the field), done only when
:class:`~components.frame_buffers.FrameBuffers` has no free buffer of that slot to hand out again.

Sequence number: the first 8 bytes of ``data`` hold the scan sequence number (0, 1, 2 ...) as a little-endian
uint64. **This overwrites x and y of point 0**: x of point 0 is the low 32 bits of the sequence number read as
a float32 (a tiny denormal, finite for sequence < 0x7F800000), y its high 32 bits (0.0). Consumers that care
about geometry should skip point 0.
"""
from __future__ import annotations

import math
from array import array
from typing import Any

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from components.bounds import Bounds
from components.frame_buffers import FRAME_SLOTS, FrameBuffers
from components.sensor_driver import MAX_FRAME_BYTES, SensorDriver, stamp_from_ns

#: (name, offset, PointField datatype) of each field; see the module docstring.
FIELDS = (
    ("x", 0, PointField.FLOAT32),
    ("y", 4, PointField.FLOAT32),
    ("z", 8, PointField.FLOAT32),
    ("intensity", 12, PointField.FLOAT32),
    ("ring", 16, PointField.UINT16),
    ("time", 20, PointField.FLOAT32),
)
POINT_STEP = 24
#: numpy view of one point.
POINT_DTYPE = np.dtype({
    "names": ["x", "y", "z", "intensity", "ring", "time"],
    "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
    "offsets": [0, 4, 8, 12, 16, 20],
    "itemsize": POINT_STEP,
})
POINTS = Bounds(1, MAX_FRAME_BYTES // POINT_STEP, "points")
RINGS = Bounds(1, 1024, "rings")
#: Offset in the noise pool, in points, between the scans of two consecutive slots.
OFFSET_STRIDE = 7919
NOISE_SIGMA = 0.01
VERTICAL_FOV_DEG = 30.0
SENSOR_HEIGHT = 1.8
ROOM_HALF_X, ROOM_HALF_Y, ROOM_HEIGHT = 20.0, 14.0, 4.0


def scan_template(points: int, rings: int, rate: float) -> np.ndarray:
    """The noise-free scan as a ``POINT_DTYPE`` array (the sequence number is not written)."""
    columns = math.ceil(points / rings)
    index = np.arange(points)
    column = index // rings
    ring = index % rings
    azimuth = 2.0 * np.pi * column / columns
    if rings > 1:
        elevation = np.radians(-VERTICAL_FOV_DEG / 2.0 + VERTICAL_FOV_DEG * ring / (rings - 1))
    else:
        elevation = np.zeros(points)
    dx = np.cos(elevation) * np.cos(azimuth)
    dy = np.cos(elevation) * np.sin(azimuth)
    dz = np.sin(elevation)
    with np.errstate(divide="ignore"):
        hit = np.minimum(ROOM_HALF_X / np.abs(dx), ROOM_HALF_Y / np.abs(dy))
        floor = np.where(dz < 0, SENSOR_HEIGHT / -dz, np.inf)
        ceiling = np.where(dz > 0, (ROOM_HEIGHT - SENSOR_HEIGHT) / dz, np.inf)
    distance = np.minimum(hit, np.minimum(floor, ceiling))
    on_wall = hit <= np.minimum(floor, ceiling)
    scan = np.zeros(points, dtype=POINT_DTYPE)
    scan["x"] = distance * dx
    scan["y"] = distance * dy
    scan["z"] = distance * dz
    pattern = np.random.default_rng(0x11DA).uniform(0.0, 40.0, points)
    scan["intensity"] = np.where(on_wall, 120.0, 30.0) + pattern + 80.0 * (column % 64 < 4)
    scan["ring"] = ring
    scan["time"] = column / columns / rate
    return scan


class LidarDriver(SensorDriver):
    """Simulated lidar publishing PointCloud2 scans with x, y, z, intensity, ring, time."""

    DEFAULT_TOPIC = "~/points"
    DEFAULT_FRAME_ID = "lidar"
    _scans: FrameBuffers | None = None
    RATE_PARAMETER = "rate"
    DEFAULT_RATE = 10.0

    def __init__(self, node_name: str = "lidar", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)

    def configure(self) -> None:
        self.points_per_scan = self.declare_int_parameter("points_per_scan", 32768, "points per scan", POINTS)
        self.rings = self.declare_int_parameter("rings", 32, "number of laser rings", RINGS)
        if self.rings > self.points_per_scan:
            raise ValueError(f"parameter 'rings' ({self.rings}) must not exceed points_per_scan "
                             f"({self.points_per_scan})")
        self.row_step = self.frame_bytes = self.points_per_scan * POINT_STEP
        self._noise = np.random.default_rng(0x401D).normal(
            0.0, NOISE_SIGMA, (self.points_per_scan + (FRAME_SLOTS - 1) * OFFSET_STRIDE, 3)).astype(np.float32)
        self._noise.flags.writeable = False
        self.rate_changed()
        self.publisher = self.create_publisher(PointCloud2, self.topic, self.qos_profile)

    def destroy_node(self) -> None:
        if self._scans is not None:  # None: construction failed before configure() made the ring
            self._scans.clear()
        super().destroy_node()

    def rate_changed(self) -> None:
        """The point times span one scan period: rebuild the noise-free scan for the (new) rate, and start a
        new ring of buffers (the old buffers hold the old times)."""
        self._template = scan_template(self.points_per_scan, self.rings, self.rate).tobytes()  # immutable
        self._scans = FrameBuffers(FRAME_SLOTS, self._fill_scan)

    def _fill_scan(self, slot: int) -> array:
        n = self.points_per_scan
        data = array("B")
        data.frombytes(self._template)
        xyz = np.ndarray((n, 3), dtype="<f4", buffer=data, strides=(POINT_STEP, 4))
        xyz += self._noise[slot * OFFSET_STRIDE:slot * OFFSET_STRIDE + n]
        del xyz  # release the buffer export before handing the array over
        return data

    def make_cloud(self, sequence: int, stamp_ns: int) -> PointCloud2:
        """A fresh PointCloud2 whose data buffer nobody else holds; sequence number in data[0:8] (uint64 LE)."""
        n = self.points_per_scan
        data = self._scans.take(sequence)
        data[0:8] = array("B", (sequence & 0xFFFFFFFFFFFFFFFF).to_bytes(8, "little"))
        msg = PointCloud2(check_fields=True)  # keeps the array.array as is (see CameraDriver.make_image)
        msg.header = Header(stamp=stamp_from_ns(stamp_ns), frame_id=self.frame_id)
        msg.height = 1
        msg.width = n
        msg.fields = [PointField(name=name, offset=offset_, datatype=datatype, count=1)
                      for name, offset_, datatype in FIELDS]
        msg.is_bigendian = False
        msg.point_step = POINT_STEP
        msg.row_step = self.row_step
        msg.data = data
        msg.is_dense = True
        return msg

    def publish_frame(self) -> None:
        stamp_ns = self.capture_ns()
        self.publisher.publish(self.make_cloud(self.next_sequence(self.publisher), stamp_ns))
