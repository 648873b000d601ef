"""A one-copy CDR deserializer for the big sensor messages a player replays.

The player turns each recorded CDR message into a Python message object. ``rclpy.serialization.
deserialize_message`` copies a message's ``data`` payload three times on the way (CDR buffer to the C
struct, C struct to a temporary ``bytes``, ``bytes`` into the message's ``array.array``), which for 1080p
images is most of the cost of replaying them. For the few types whose size is all in one ``uint8[]``
payload (``sensor_msgs/msg/Image``, ``PointCloud2`` and ``CompressedImage``) this module reads the small
fields itself and copies the payload once, straight from the CDR buffer into the message's own
``data`` array with ``array.frombytes`` (what rclpy's generated ``convert_to_py`` does too, from its
temporary ``bytes``). The message is built by its constructor and filled through its public
attributes, so it is the object rclpy would return: the same Python type for every field, ``==`` equal,
and re-serialized to the same bytes (up to alignment padding, which serializers leave uninitialized).
No setter is bypassed, and none is needed: assigning ``msg.data`` instead would cost a second copy (the
setter builds a new ``array('B')`` from whatever it gets, ``bytes`` or an array alike) or, given a
``memoryview`` or numpy array, a conversion element by element three orders of magnitude slower
(``benchmarks/deserialize.py`` measures each way). The message owns its payload: it never references
the input buffer, which is free to be reused or resized once ``deserialize`` returns or raises.

What is read is what rmw_fastrtps_cpp's C type support reads (checked against ``deserialize_message``
in ``tests/test_cdr_read.py``): plain CDR (XCDR1) after the 4-byte encapsulation header, whose second
byte says the byte order (``00 00`` big endian, ``00 01`` little endian; the two option bytes are
ignored); primitives aligned to their size relative to the end of that header; a ``string`` as a
``uint32`` byte count and the bytes, where a count of 0 is the empty string, a final NUL is optional and
the string ends at its first NUL, invalid UTF-8 decoding to U+FFFD; a ``bool`` true for any non-zero
byte; sequences as a ``uint32`` element count and the elements; bytes after the message (the padding of
an RTPS sample) ignored. Any other encapsulation (parameter lists, XCDR2), and every other type, go to
``deserialize_message``. Malformed input (a count or length running past the end, a short buffer, an
unknown encapsulation) raises :class:`ValueError` naming the type, on either path.
"""
from __future__ import annotations

import functools
import struct
from collections.abc import Callable
from typing import Any, NamedTuple

from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CompressedImage, Image, PointCloud2, PointField
from std_msgs.msg import Header

__all__ = ["deserialize"]


class _Structs(NamedTuple):
    """The struct formats the decoders read, in one byte order."""

    u32: struct.Struct
    u32_pair: struct.Struct
    stamp: struct.Struct  # builtin_interfaces/Time: int32 sec, uint32 nanosec

    @classmethod
    def of(cls, byte_order: str) -> _Structs:
        return cls(struct.Struct(byte_order + "I"), struct.Struct(byte_order + "II"), struct.Struct(byte_order + "iI"))


#: Encapsulation header bytes 0-1 of plain CDR: big endian, little endian.
_PLAIN_CDR = {b"\x00\x00": _Structs.of(">"), b"\x00\x01": _Structs.of("<")}
_HEADER_SIZE = 4
#: Fewest bytes one sensor_msgs/PointField takes: an empty name's length, offset, datatype and its padding,
#: count.
_MIN_POINT_FIELD_SIZE = 4 + 4 + 4 + 4


class _Reader:
    """A cursor over one CDR message; every read checks the bounds and names the field on failure.

    Positions are into the whole message, encapsulation header included: the body starts at 4, so
    alignment relative to the body is alignment of the absolute position.
    """

    __slots__ = ("end", "pos", "structs", "type_name", "view")

    def __init__(self, view: memoryview, type_name: str, structs: _Structs) -> None:
        self.view = view
        self.type_name = type_name
        self.structs = structs
        self.pos = _HEADER_SIZE
        self.end = len(view)

    def take(self, size: int, what: str) -> int:
        """Start of the next ``size`` bytes (``what`` names them for the error), moving past them."""
        start = self.pos
        if start + size > self.end:
            raise ValueError(f"malformed {self.type_name}: {what} needs {size} bytes at byte {start} but the "
                             f"message has only {self.end} bytes")
        self.pos = start + size
        return start

    def _align4(self) -> None:
        self.pos = (self.pos + 3) & -4

    def uint8(self, what: str) -> int:
        return self.view[self.take(1, what)]

    def uint32(self, what: str) -> int:
        self._align4()
        return self.structs.u32.unpack_from(self.view, self.take(4, what))[0]

    def uint32_pair(self, what: str) -> tuple[int, int]:
        self._align4()
        return self.structs.u32_pair.unpack_from(self.view, self.take(8, what))

    def string(self, what: str) -> str:
        """A string as Fast-CDR and rosidl's C strings read it: up to the first NUL, final NUL optional."""
        length = self.uint32(what)
        start = self.take(length, what)
        raw = bytes(self.view[start:start + length])
        nul = raw.find(0)
        return (raw if nul < 0 else raw[:nul]).decode("utf-8", "replace")

    def sequence_length(self, what: str, min_element_size: int) -> int:
        """A sequence's element count, rejected at once if its elements cannot fit in what is left."""
        count = self.uint32(what)
        if count * min_element_size > self.end - self.pos:
            raise ValueError(f"malformed {self.type_name}: {what} counts {count} elements, which cannot fit in the "
                             f"{self.end - self.pos} bytes left after byte {self.pos}")
        return count

    def octets_into(self, target: Any, what: str) -> None:
        """A ``uint8[]`` appended to the ``array('B')`` ``target``: the one copy of the payload."""
        length = self.uint32(what)
        start = self.take(length, what)
        target.frombytes(self.view[start:start + length])


def _header(reader: _Reader, header: Header) -> None:
    """``std_msgs/Header`` at the start of the body (offset 0: the stamp needs no padding)."""
    stamp = header.stamp
    stamp.sec, stamp.nanosec = reader.structs.stamp.unpack_from(reader.view, reader.take(8, "header.stamp"))
    header.frame_id = reader.string("header.frame_id")


def _image(reader: _Reader) -> Image:
    msg = Image()
    _header(reader, msg.header)
    msg.height, msg.width = reader.uint32_pair("height and width")
    msg.encoding = reader.string("encoding")
    msg.is_bigendian = reader.uint8("is_bigendian")
    msg.step = reader.uint32("step")
    reader.octets_into(msg.data, "data")
    return msg


def _point_field(reader: _Reader) -> PointField:
    name = reader.string("fields[].name")
    offset = reader.uint32("fields[].offset")
    datatype = reader.uint8("fields[].datatype")
    return PointField(name=name, offset=offset, datatype=datatype, count=reader.uint32("fields[].count"))


def _point_cloud2(reader: _Reader) -> PointCloud2:
    msg = PointCloud2()
    _header(reader, msg.header)
    msg.height, msg.width = reader.uint32_pair("height and width")
    count = reader.sequence_length("fields", _MIN_POINT_FIELD_SIZE)
    msg.fields = [_point_field(reader) for _ in range(count)]
    msg.is_bigendian = reader.uint8("is_bigendian") != 0
    msg.point_step, msg.row_step = reader.uint32_pair("point_step and row_step")
    reader.octets_into(msg.data, "data")
    msg.is_dense = reader.uint8("is_dense") != 0
    return msg


def _compressed_image(reader: _Reader) -> CompressedImage:
    msg = CompressedImage()
    _header(reader, msg.header)
    msg.format = reader.string("format")
    reader.octets_into(msg.data, "data")
    return msg


# Exact types only: a subclass may add fields these decoders would not read.
_DECODERS: dict[type, Callable[[_Reader], Any]] = {
    Image: _image,
    PointCloud2: _point_cloud2,
    CompressedImage: _compressed_image,
}


@functools.cache
def _type_name(msg_class: type) -> str:
    """``pkg/msg/Name`` of a generated message class (its module is ``pkg.msg._name``)."""
    package, kind, *_ = msg_class.__module__.split(".") + ["", ""]
    return f"{package}/{kind}/{msg_class.__name__}" if kind else msg_class.__qualname__


def _with_rclpy(data: bytes | memoryview, msg_class: type) -> Any:
    """``deserialize_message`` (which takes only ``bytes``), its failure as a ValueError naming the type."""
    raw = data if type(data) is bytes else bytes(data)
    try:
        return deserialize_message(raw, msg_class)
    except RuntimeError as error:  # rclpy's RMWError
        raise ValueError(f"malformed {_type_name(msg_class)}: rclpy could not deserialize {len(raw)} bytes: "
                         f"{error}") from error


def deserialize(data: bytes | memoryview, msg_class: type) -> Any:
    """The ``msg_class`` message that the CDR message ``data`` holds, as ``deserialize_message`` returns it.

    Image, PointCloud2 and CompressedImage in plain CDR are read here, their payload copied once into
    the message; everything else goes to ``deserialize_message`` (a memoryview is copied to ``bytes``
    for it first). ``data`` may be any buffer of bytes (``bytes``, ``bytearray``, ``mmap``, a view of
    one); the message never references it. Raises ValueError if ``data`` is not a valid message.
    """
    decoder = _DECODERS.get(msg_class)
    if decoder is None:
        return _with_rclpy(data, msg_class)
    # Released on the way out, even by an exception whose traceback lives on: a bytearray stays resizable.
    with memoryview(data) as given, given.cast("B") as view:
        structs = _PLAIN_CDR.get(bytes(view[:2])) if len(view) >= _HEADER_SIZE else None
        if structs is None:
            return _with_rclpy(view, msg_class)
        return decoder(_Reader(view, _type_name(msg_class), structs))
