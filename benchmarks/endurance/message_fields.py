"""What a soak message says: its stream, capture stamp and sequence number, parsed from its CDR bytes.

The drivers number their messages (Image and PointCloud2: ``data[0:8]``; Imu: ``orientation_covariance[1]``);
the player's bag holds std_msgs/String "0", "1", ...; CameraInfo has no number, its stamp pairs it with its
image. The parser needs only the first bytes of a message (:data:`HEAD_BYTES`), and is checked against rosbags'
own deserialization (:func:`fields_by_rosbags`) on a message of every topic of every file.
"""
from __future__ import annotations

import struct
from typing import Any, Optional

IMAGE = "sensor_msgs/msg/Image"
CLOUD = "sensor_msgs/msg/PointCloud2"
IMU = "sensor_msgs/msg/Imu"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
STRING = "std_msgs/msg/String"
#: Message types whose stamps are kept: an image and its CameraInfo share one.
CAMERA_TYPES = (IMAGE, CAMERA_INFO)
#: Bytes of a message's start that hold every field parse_fields reads, for the soak's types and names.
HEAD_BYTES = 512
_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")
_F64 = struct.Struct("<d")

#: A stream: (topic, header.frame_id); one driver instance publishes one stream per topic.
Stream = tuple[str, str]
#: What one message says: (capture stamp ns, frame_id, sequence number or None).
Fields = tuple[int, str, Optional[int]]


class _Cdr:
    """A cursor over little-endian CDR (alignment counts from the end of the 4-byte encapsulation header)."""

    def __init__(self, data: bytes | memoryview) -> None:
        if data[1] != 1:
            raise ValueError("only little-endian CDR is expected")
        self.data = data
        self.pos = 4

    def _align(self, size: int) -> None:
        self.pos += -(self.pos - 4) % size

    def u32(self) -> int:
        self._align(4)
        (value,) = _U32.unpack_from(self.data, self.pos)
        self.pos += 4
        return value

    def f64(self) -> float:
        self._align(8)
        (value,) = _F64.unpack_from(self.data, self.pos)
        self.pos += 8
        return value

    def skip(self, size: int) -> None:
        self.pos += size

    def string(self) -> str:
        length = self.u32()
        text = bytes(self.data[self.pos:self.pos + max(0, length - 1)]).decode()
        self.pos += length
        return text

    def header(self) -> tuple[int, str]:
        sec, nanosec = _STAMP.unpack_from(self.data, self.pos)
        self.pos += 8
        return sec * 1_000_000_000 + nanosec, self.string()

    def leading_u64_of_sequence(self) -> int:
        """The first 8 bytes of a byte sequence (its length first), little-endian: a driver's number."""
        self.u32()
        return int.from_bytes(self.data[self.pos:self.pos + 8], "little")


def parse_fields(msgtype: str, data: bytes | memoryview) -> Fields:
    """(stamp, frame_id, sequence number) of one serialized message of the soak's types."""
    cdr = _Cdr(data)
    if msgtype == STRING:
        return 0, "", int(cdr.string())
    stamp, frame_id = cdr.header()
    if msgtype == IMAGE:
        cdr.u32(), cdr.u32(), cdr.string()  # height, width, encoding
        cdr.skip(1)                         # is_bigendian
        cdr.u32()                           # step
        return stamp, frame_id, cdr.leading_u64_of_sequence()
    if msgtype == CLOUD:
        cdr.u32(), cdr.u32()                # height, width
        for _ in range(cdr.u32()):          # fields: name, offset, datatype, count
            cdr.string(), cdr.u32(), cdr.skip(1), cdr.u32()
        cdr.skip(1)                         # is_bigendian
        cdr.u32(), cdr.u32()                # point_step, row_step
        return stamp, frame_id, cdr.leading_u64_of_sequence()
    if msgtype == IMU:
        for _ in range(4 + 1):              # orientation, orientation_covariance[0]
            cdr.f64()
        return stamp, frame_id, int(cdr.f64())
    return stamp, frame_id, None


def fields_by_rosbags(typestore: Any, data: bytes, msgtype: str) -> Fields:
    """The same fields, from rosbags' own deserialization."""
    msg = typestore.deserialize_cdr(data, msgtype)
    if msgtype == STRING:
        return 0, "", int(msg.data)
    stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
    if msgtype in (IMAGE, CLOUD):
        return stamp, msg.header.frame_id, int.from_bytes(bytes(msg.data[:8]), "little")
    if msgtype == IMU:
        return stamp, msg.header.frame_id, int(msg.orientation_covariance[1])
    return stamp, msg.header.frame_id, None
