"""A copy-free CDR serializer for the recorder's big sensor messages.

The recorder's writer thread turns intra-process message objects into CDR before they go to the bag.
``rclpy.serialization.serialize_message`` copies a message's ``data`` buffer three times (Python
object to C struct, C struct to the CDR buffer, CDR buffer to ``bytes``), which for 1080p images at
60 Hz is a large share of the recorder's CPU on a small machine. For the few types whose size is all in
one ``uint8[]`` payload (``sensor_msgs/msg/Image``, ``PointCloud2`` and ``CompressedImage``) this
module writes the small fields itself and returns the payload as a ``memoryview`` of ``msg.data``:
:class:`SerializedBuffers` (prefix bytes, the view, suffix bytes). The MCAP storage writes those
buffers to the file one after the other, so the payload is copied only by the kernel; anything else
that needs one buffer gets it from ``bytes(buffers)`` (one copy).

``sensor_msgs/msg/Imu`` and ``CameraInfo`` are small but come at high rates (an IMU at kilohertz, a
``camera_info`` with every frame), where ``serialize_message`` (a C struct built field by field, then the
CDR, then the padding check of :func:`_wire_exact`) is most of the writer's cost per message; they are
written here with ``struct`` and the float64 arrays' own bytes.

The encoding is what rmw_fastrtps_cpp produces: XCDR1 little endian with the encapsulation header
``00 01 00 00``, primitives aligned to their size relative to the end of that header, strings as a
``uint32`` length that counts the terminating NUL, the UTF-8 bytes and the NUL, sequences as a
``uint32`` element count and the elements. Alignment padding is written as zeros (Fast-CDR leaves it
uninitialized, so rclpy's bytes differ from these only there; the samples Fast DDS publishes have them
zeroed, like these). Every other message type, and messages whose ``data`` is not a byte buffer, go to
``serialize_message``, cut to the size of the message and with its padding zeroed (:mod:`.cdr_size`):
rclpy returns rmw_fastrtps' size estimate, which can run past the serialized data.
"""
from __future__ import annotations

import struct
import sys
from array import array
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu, PointCloud2
from std_msgs.msg import Header

from baglib.format.cdr_size import serialized_layout

__all__ = ["CDR_LE_HEADER", "MIN_BUFFERS_SIZE", "CdrData", "SerializedBuffers", "serialize"]

#: Encapsulation header of little-endian plain CDR (what rmw_fastrtps_cpp and rosbag2 write).
CDR_LE_HEADER = b"\x00\x01\x00\x00"
#: Payloads at least this large stay views (:class:`SerializedBuffers`); smaller messages are joined
#: into ``bytes``, where one small copy costs less than the extra objects a consumer handles.
MIN_BUFFERS_SIZE = 64 * 1024

_STAMP = struct.Struct("<iI")
_U32 = struct.Struct("<I")
_U32_PAIR = struct.Struct("<II")
_PADDING = (b"", b"\x00\x00\x00", b"\x00\x00", b"\x00")
_QUATERNION = struct.Struct("<4d")
_VECTOR3 = struct.Struct("<3d")
_FLOAT64 = np.dtype(np.float64)
_U32_QUAD_BOOL = struct.Struct("<IIII?")

Buffer = bytes | bytearray | memoryview


class SerializedBuffers:
    """One serialized message held as consecutive buffers, the big one a view of the message's data.

    Joining them (``bytes(buffers)``) gives exactly the CDR message. The views keep the message's
    ``data`` array alive and unresizable while this object lives; the recorder drops it as soon as the
    storage has written it. ``len()`` is the serialized size in bytes.
    """

    __slots__ = ("buffers", "nbytes")

    def __init__(self, buffers: tuple[Buffer, ...]) -> None:
        self.buffers = buffers
        self.nbytes = sum(len(buffer) for buffer in buffers)

    def __len__(self) -> int:
        return self.nbytes

    def __iter__(self) -> Iterator[Buffer]:
        return iter(self.buffers)

    def __bytes__(self) -> bytes:
        return b"".join(self.buffers)

    def __repr__(self) -> str:
        return f"SerializedBuffers({self.nbytes} bytes in {len(self.buffers)} buffers)"


def _align4(buffer: bytearray) -> None:
    """Pad with zeros to a multiple of 4 (relative to the 4-byte encapsulation header, also aligned)."""
    buffer += _PADDING[len(buffer) & 3]


def _string(buffer: bytearray, value: str) -> None:
    """A CDR string. Like rosidl's C conversion (strlen of the UTF-8 bytes) it ends at the first NUL."""
    raw = value.encode()
    nul = raw.find(b"\x00")
    if nul >= 0:
        raw = raw[:nul]
    _align4(buffer)
    buffer += _U32.pack(len(raw) + 1)
    buffer += raw
    buffer += b"\x00"


def _header(buffer: bytearray, header: Header) -> None:
    """``std_msgs/Header`` at the start of the body (offset 0, so the stamp needs no padding)."""
    stamp = header.stamp
    buffer += _STAMP.pack(stamp.sec, stamp.nanosec)
    _string(buffer, header.frame_id)


def _payload(data: Any) -> memoryview | None:
    """``data`` as a flat view of bytes, or ``None`` if it is not a contiguous byte buffer."""
    try:
        view = memoryview(data)
    except TypeError:
        return None
    if not view.c_contiguous:
        return None
    return view if view.format == "B" and view.ndim == 1 else view.cast("B")


#: What the storages accept as one serialized message.
CdrData = bytes | bytearray | memoryview | SerializedBuffers


def _finish(prefix: bytearray, data: memoryview, suffix: bytes) -> bytes | SerializedBuffers:
    """Prefix (ending with the sequence length), payload, suffix: as views if the payload is big."""
    if len(data) >= MIN_BUFFERS_SIZE:
        return SerializedBuffers((bytes(prefix), data, suffix) if suffix else (bytes(prefix), data))
    prefix += data
    prefix += suffix
    return bytes(prefix)


def _start(msg: Any) -> tuple[memoryview, bytearray] | None:
    """The payload view and a buffer holding the encapsulation header and the std_msgs/Header."""
    data = _payload(msg.data)
    if data is None:
        return None
    buffer = bytearray(CDR_LE_HEADER)
    _header(buffer, msg.header)
    return data, buffer


def _image(msg: Image) -> bytes | SerializedBuffers | None:
    if (start := _start(msg)) is None:
        return None
    data, buffer = start
    _align4(buffer)
    buffer += _U32_PAIR.pack(msg.height, msg.width)
    _string(buffer, msg.encoding)
    buffer.append(msg.is_bigendian)
    _align4(buffer)
    buffer += _U32_PAIR.pack(msg.step, len(data))
    return _finish(buffer, data, b"")


def _point_cloud2(msg: PointCloud2) -> bytes | SerializedBuffers | None:
    if (start := _start(msg)) is None:
        return None
    data, buffer = start
    _align4(buffer)
    fields = msg.fields
    buffer += _U32_PAIR.pack(msg.height, msg.width)
    buffer += _U32.pack(len(fields))
    for field in fields:  # sensor_msgs/PointField: string name, uint32 offset, uint8 datatype, uint32 count
        _string(buffer, field.name)
        _align4(buffer)
        buffer += _U32.pack(field.offset)
        buffer.append(field.datatype)
        _align4(buffer)
        buffer += _U32.pack(field.count)
    buffer.append(1 if msg.is_bigendian else 0)
    _align4(buffer)
    buffer += _U32_PAIR.pack(msg.point_step, msg.row_step)
    buffer += _U32.pack(len(data))
    return _finish(buffer, data, b"\x01" if msg.is_dense else b"\x00")


def _compressed_image(msg: CompressedImage) -> bytes | SerializedBuffers | None:
    if (start := _start(msg)) is None:
        return None
    data, buffer = start
    _string(buffer, msg.format)
    _align4(buffer)
    buffer += _U32.pack(len(data))
    return _finish(buffer, data, b"")


def _float64s(values: Any, count: int) -> bytes:
    """``count`` float64 values as CDR: a fixed ``float64[count]`` or the elements of a ``sequence<double>``.

    rclpy's setters keep every accepted value as a native float64 numpy array (fixed arrays) or an
    ``array('d')`` (sequences), whose ``tobytes()`` is the little-endian CDR of the values on this
    little-endian platform. Anything else was put into the slot behind the setter's back (rclpy's own
    serializer crashes the process on a list there); it is packed value by value, and raises
    ``struct.error`` unless it is ``count`` numbers.
    """
    if type(values) is np.ndarray and values.dtype == _FLOAT64 and values.size == count:
        return values.tobytes()
    if type(values) is array and values.typecode == "d" and len(values) == count:
        return values.tobytes()
    return struct.pack(f"<{count}d", *values)


def _align8(buffer: bytearray) -> None:
    """Pad with zeros to a multiple of 8 within the body (the 4-byte encapsulation header is not counted)."""
    buffer += bytes(-(len(buffer) - len(CDR_LE_HEADER)) & 7)


def _imu(msg: Imu) -> bytes:
    """Header; orientation and its covariance; angular_velocity and its; linear_acceleration and its."""
    buffer = bytearray(CDR_LE_HEADER)
    _header(buffer, msg.header)
    _align8(buffer)
    o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    return b"".join((buffer, _QUATERNION.pack(o.x, o.y, o.z, o.w), _float64s(msg.orientation_covariance, 9),
                     _VECTOR3.pack(w.x, w.y, w.z), _float64s(msg.angular_velocity_covariance, 9),
                     _VECTOR3.pack(a.x, a.y, a.z), _float64s(msg.linear_acceleration_covariance, 9)))


def _camera_info(msg: CameraInfo) -> bytes:
    """Header, size, distortion model and ``d`` (rclpy's ``array('d')``), k, r, p, binning, roi.

    The 8-alignment after ``d``'s length is the first double's: ``d[0]`` or, with an empty ``d``, ``k[0]``.
    """
    buffer = bytearray(CDR_LE_HEADER)
    _header(buffer, msg.header)
    _align4(buffer)
    buffer += _U32_PAIR.pack(msg.height, msg.width)
    _string(buffer, msg.distortion_model)
    _align4(buffer)
    d = msg.d
    buffer += _U32.pack(len(d))
    _align8(buffer)
    buffer += _float64s(d, len(d))
    roi = msg.roi
    return b"".join((buffer, _float64s(msg.k, 9), _float64s(msg.r, 9), _float64s(msg.p, 12),
                     _U32_PAIR.pack(msg.binning_x, msg.binning_y),
                     _U32_QUAD_BOOL.pack(roi.x_offset, roi.y_offset, roi.height, roi.width, roi.do_rectify)))


# Exact types only: a subclass may add fields these encoders would not write.
_ENCODERS: dict[type, Callable[[Any], bytes | SerializedBuffers | None]] = {
    Image: _image,
    PointCloud2: _point_cloud2,
    CompressedImage: _compressed_image,
}
if sys.byteorder == "little":  # x86_64, the platform this project supports; elsewhere rclpy serializes them
    _ENCODERS.update({Imu: _imu, CameraInfo: _camera_info})


def _wire_exact(msg: Any) -> bytes | memoryview:
    """``serialize_message``'s bytes cut to the message and with zeroed padding: what the wire carries.

    rclpy returns rmw_fastrtps' size *estimate* as the length, which can run past the serialized data,
    and leaves alignment padding uninitialized; :func:`.cdr_size.serialized_layout` says where both are.
    Padding is only rewritten when it is not zero already, and big messages are cut as a view, so a big
    payload is copied again only if its padding needs zeroing.
    """
    data = serialize_message(msg)
    size, padding = serialized_layout(msg)
    dirty = [(start, stop) for start, stop in padding if data.count(0, start, stop) != stop - start]
    if dirty:
        fixed = bytearray(memoryview(data)[:size])
        for start, stop in dirty:
            fixed[start:stop] = bytes(stop - start)
        return bytes(fixed) if size < MIN_BUFFERS_SIZE else memoryview(fixed).toreadonly()
    if size == len(data):
        return data
    return memoryview(data)[:size] if size >= MIN_BUFFERS_SIZE else data[:size]


def serialize(msg: Any) -> bytes | memoryview | SerializedBuffers:
    """The CDR serialization of ``msg``: exactly the sample a raw subscription would receive for it.

    Imu and CameraInfo messages are written here too (as ``bytes``). Image, PointCloud2 and CompressedImage
    messages with a payload of at least :data:`MIN_BUFFERS_SIZE` bytes come back as :class:`SerializedBuffers`
    that reference ``msg.data``; other messages of at least that size whose ``serialize_message`` output had to be cut
    or cleaned as a read-only ``memoryview``; everything else as ``bytes``.
    """
    encoder = _ENCODERS.get(type(msg))
    if encoder is not None:
        result = encoder(msg)
        if result is not None:
            return result
    return _wire_exact(msg)
