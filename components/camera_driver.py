"""Simulated camera: publishes ``sensor_msgs/Image`` plus ``sensor_msgs/CameraInfo`` at ``fps``.

Parameters (validated at construction; a bad value raises ValueError naming the parameter and its range).
``fps`` and ``frame_id`` can be changed at run time (``ros2 param set``); the others are read-only:

==============  ===============  =====================================================================
``width``       640              image width in pixels (1 ... 16384)
``height``      480              image height in pixels (1 ... 16384); a frame is at most 64 MiB
``encoding``    ``'rgb8'``       see :data:`ENCODINGS` (rgb8, bgr8, rgba8, bgra8, rgb16 ..., mono8, mono16,
                                 bayer_*8/16, yuv422 (UYVY), yuv422_yuy2, uyvy, yuyv) and the generic
                                 ``8UC1`` ... ``64FC4`` forms
``fps``         30.0             frames per second (0.01 ... 2000, at most 1 GB/s of frames)
``frame_id``    ``'camera'``     header.frame_id of image and camera_info
``topic``       ``'~/image_raw'``  image topic; camera_info goes to the sibling topic (``~/camera_info``)
``qos``         ``'reliable'``   ``'reliable'`` or ``'sensor_data'`` (best effort), for both topics
``content``     ``'random'``     ``'random'`` (below) or ``'photo'``: a window panning and zooming across a
                                 real photograph, with sensor noise (:mod:`components.photo_content`;
                                 rgb8, bgr8, mono8, YUV 4:2:2 and bayer_*8); for 16UC1 and mono16 a
                                 smooth range image, what a depth camera sees (:mod:`components.depth_content`)
==============  ===============  =====================================================================

Random content: random bytes. A pool of random bytes (the frame size plus a few KiB) is generated once;
frame ``n`` is the slice of the pool at offset ``(n % FRAME_SLOTS) * OFFSET_STRIDE``, so consecutive frames
differ. Its buffer is an ``array.array('B')``, which the message keeps as is (never a numpy array: assigning
one to a ``uint8[]`` field is ~200x slower), taken from :class:`~components.frame_buffers.FrameBuffers`: the
slot's buffer again once nobody holds it, so that a frame costs no memcpy of its pixels, else a fresh copy.

Sequence number: the first 8 bytes of ``Image.data`` hold the image sequence number (0, 1, 2 ...) as a
little-endian uint64. The matching CameraInfo has the same ``header.stamp`` as its image.
"""
from __future__ import annotations

import re
import sys
from array import array
from typing import Any, Optional

import numpy as np
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from components.bounds import Bounds
from components.depth_content import DepthContent
from components.frame_buffers import FRAME_SLOTS, FrameBuffers
from components.image_encoder.pixel_formats import FORMATS
from components.photo_content import PhotoContent
from components.sensor_driver import FIXED_GEOMETRY, MAX_FRAME_BYTES, SensorDriver, stamp_from_ns

#: Named encodings: bytes per pixel, and the (width, height) divisors the image size must respect.
ENCODINGS: dict[str, tuple[int, tuple[int, int]]] = {
    "rgb8": (3, (1, 1)), "bgr8": (3, (1, 1)), "rgba8": (4, (1, 1)), "bgra8": (4, (1, 1)),
    "rgb16": (6, (1, 1)), "bgr16": (6, (1, 1)), "rgba16": (8, (1, 1)), "bgra16": (8, (1, 1)),
    "mono8": (1, (1, 1)), "mono16": (2, (1, 1)),
    "bayer_rggb8": (1, (2, 2)), "bayer_bggr8": (1, (2, 2)), "bayer_gbrg8": (1, (2, 2)), "bayer_grbg8": (1, (2, 2)),
    "bayer_rggb16": (2, (2, 2)), "bayer_bggr16": (2, (2, 2)), "bayer_gbrg16": (2, (2, 2)),
    "bayer_grbg16": (2, (2, 2)),
    # 4:2:2 packed formats: 2 bytes per pixel, pixels come in pairs.
    "yuv422": (2, (2, 1)), "yuv422_yuy2": (2, (2, 1)), "uyvy": (2, (2, 1)), "yuyv": (2, (2, 1)),
}
_GENERIC_ENCODING = re.compile(r"^(8U|8S|16U|16S|32S|32F|64F)C([1-4])$")
_GENERIC_DEPTH_BYTES = {"8U": 1, "8S": 1, "16U": 2, "16S": 2, "32S": 4, "32F": 4, "64F": 8}

#: Image width and height in pixels (16K); the frame size is bounded by MAX_FRAME_BYTES as well.
SIDE = Bounds(1, 16384, "pixels")
#: Frame sizes accepted, in bytes: room for the sequence number, and one driver's share of memory.
FRAME_BYTES = Bounds(8, MAX_FRAME_BYTES, "bytes")
#: Offset in the pool, in bytes, between the frames of two consecutive slots.
OFFSET_STRIDE = 4099
#: Values of the ``content`` parameter.
CONTENTS = ("random", "photo")
#: Horizontal field of view of the simulated pinhole camera, used for CameraInfo.
HORIZONTAL_FOV_DEG = 60.0


def encoding_info(encoding: str) -> Optional[tuple[str, int, tuple[int, int]]]:
    """``(canonical name, bytes per pixel, (width divisor, height divisor))`` or None if unknown."""
    lowered = encoding.lower()
    if lowered in ENCODINGS:
        bytes_per_pixel, divisors = ENCODINGS[lowered]
        return lowered, bytes_per_pixel, divisors
    match = _GENERIC_ENCODING.match(encoding.upper())
    if match:
        depth, channels = match.groups()
        return f"{depth}C{channels}", _GENERIC_DEPTH_BYTES[depth] * int(channels), (1, 1)
    return None


def camera_info_topic_for(image_topic: str) -> str:
    """The camera_info topic next to an image topic: ``~/image_raw`` -> ``~/camera_info``."""
    head, sep, _ = image_topic.rpartition("/")
    return f"{head}{sep}camera_info"


class CameraDriver(SensorDriver):
    """Simulated camera publishing random or photographic images and a matching CameraInfo."""

    DEFAULT_TOPIC = "~/image_raw"
    DEFAULT_FRAME_ID = "camera"
    _frames: FrameBuffers | None = None
    RATE_PARAMETER = "fps"
    DEFAULT_RATE = 30.0

    def __init__(self, node_name: str = "camera", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)

    def configure(self) -> None:
        self.width = self.declare_int_parameter("width", 640, "image width in pixels", SIDE)
        self.height = self.declare_int_parameter("height", 480, "image height in pixels", SIDE)
        requested = self.declare_string_parameter("encoding", "rgb8", "image encoding (sensor_msgs image_encodings)",
                                                  fixed=FIXED_GEOMETRY)
        info = encoding_info(requested)
        if info is None:
            raise ValueError(
                f"parameter 'encoding': unknown encoding {requested!r}; supported: {', '.join(ENCODINGS)} "
                "and 8UC1 ... 64FC4")
        self.encoding, self.bytes_per_pixel, (width_divisor, height_divisor) = info
        if self.width % width_divisor:
            raise ValueError(f"parameter 'width' must be a multiple of {width_divisor} for encoding "
                             f"{self.encoding!r}, got {self.width}")
        if self.height % height_divisor:
            raise ValueError(f"parameter 'height' must be a multiple of {height_divisor} for encoding "
                             f"{self.encoding!r}, got {self.height}")
        self.step = self.width * self.bytes_per_pixel
        self.frame_bytes = self.step * self.height
        FRAME_BYTES.check(f"'width' x 'height' x {self.bytes_per_pixel} bytes per pixel ({self.encoding}), the "
                          "frame size,", self.frame_bytes)
        self.camera_info_topic = camera_info_topic_for(self.topic)
        if self.camera_info_topic == self.topic:
            raise ValueError(f"parameter 'topic': {self.topic!r} collides with its camera_info topic")
        self.check_topic_name("topic", self.camera_info_topic)
        self.is_bigendian = 1 if sys.byteorder == "big" else 0

        self.content = self.declare_choice_parameter(
            "content", "random", CONTENTS, "frame content: 'random' bytes, or 'photo' (a window panning across a "
            "photograph, with sensor noise; a range image for 16-bit depth)", fixed=FIXED_GEOMETRY)
        if self.content == "photo":
            depth = self.encoding in FORMATS and FORMATS[self.encoding].is_depth  # 16UC1, mono16: a range image
            self._photo: PhotoContent | DepthContent | None = (
                DepthContent(self.width, self.height) if depth
                else PhotoContent(self.width, self.height, self.encoding))
            self._frames = FrameBuffers(FRAME_SLOTS, self._blank_frame)
        else:
            self._photo = None
            self._pool = np.random.default_rng(0x5EED).bytes(self.frame_bytes + (FRAME_SLOTS - 1) * OFFSET_STRIDE)
            self._pool_view = memoryview(self._pool)  # immutable bytes: nothing ever writes into the pool
            self._frames = FrameBuffers(FRAME_SLOTS, self._fill_frame)

        fx = self.width / (2.0 * np.tan(np.radians(HORIZONTAL_FOV_DEG) / 2.0))
        cx, cy = (self.width - 1) / 2.0, (self.height - 1) / 2.0
        self._k = (fx, 0.0, cx, 0.0, fx, cy, 0.0, 0.0, 1.0)
        self._r = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
        self._p = (fx, 0.0, cx, 0.0, 0.0, fx, cy, 0.0, 0.0, 0.0, 1.0, 0.0)

        self.image_publisher = self.create_publisher(Image, self.topic, self.qos_profile)
        self.camera_info_publisher = self.create_publisher(CameraInfo, self.camera_info_topic, self.qos_profile)

    def destroy_node(self) -> None:
        if self._frames is not None:  # None: construction failed before configure() made the ring
            self._frames.clear()
        super().destroy_node()

    # ------------------------------------------------------------------ frames
    def _fill_frame(self, slot: int) -> array:
        data = array("B")
        data.frombytes(self._pool_view[slot * OFFSET_STRIDE:slot * OFFSET_STRIDE + self.frame_bytes])
        return data

    def _blank_frame(self, slot: int) -> array:
        """A buffer for photo frames, which are written whole on every take."""
        return array("B", bytes(self.frame_bytes))

    def make_image(self, sequence: int, stamp_ns: int) -> Image:
        """A fresh Image whose data buffer nobody else holds; sequence number in data[0:8] (uint64 LE)."""
        data = self._frames.take(sequence)
        if self._photo is not None:
            self._photo.fill(sequence, memoryview(data))
        data[0:8] = array("B", (sequence & 0xFFFFFFFFFFFFFFFF).to_bytes(8, "little"))
        # check_fields=True: the uint8[] setter then keeps an array.array('B') as is; without it, it copies
        # the whole frame again (array.array('B', value)), ~3 ms per 1080p frame under the GIL.
        msg = Image(check_fields=True)
        msg.header = Header(stamp=stamp_from_ns(stamp_ns), frame_id=self.frame_id)
        msg.height = self.height
        msg.width = self.width
        msg.encoding = self.encoding
        msg.is_bigendian = self.is_bigendian
        msg.step = self.step
        msg.data = data
        return msg

    def make_camera_info(self, stamp_ns: int) -> CameraInfo:
        """A fresh CameraInfo of the simulated pinhole camera (no distortion)."""
        msg = CameraInfo()
        msg.header = Header(stamp=stamp_from_ns(stamp_ns), frame_id=self.frame_id)
        msg.height = self.height
        msg.width = self.width
        msg.distortion_model = "plumb_bob"
        msg.d = [0.0, 0.0, 0.0, 0.0, 0.0]
        msg.k = self._k
        msg.r = self._r
        msg.p = self._p
        return msg

    def publish_frame(self) -> None:
        stamp_ns = self.capture_ns()
        image = self.make_image(self.next_sequence(self.image_publisher), stamp_ns)
        info = self.make_camera_info(stamp_ns)
        self.image_publisher.publish(image)
        self.camera_info_publisher.publish(info)
