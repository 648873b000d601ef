"""The one-copy CDR deserializer against rclpy's ``deserialize_message``.

rclpy (rmw_fastrtps' C type support behind it) is the oracle: for every input both decode, the results
must have the same Python type in every field, be ``==`` equal, and serialize back (with rclpy, and with
the fast serializer) to the input, up to the alignment padding rclpy leaves uninitialized. Inputs are
seeded random messages of the three fast-path types in both byte orders, as rclpy's own bytes (garbage
padding), with trailing bytes, and as views of other buffers; then hand-made wire forms of strings,
booleans and encapsulations; then malformed input, where both must refuse (ours with a ValueError naming
the type). The seed is printed by every randomized test; rerun one with ``CDR_READ_SEED=<seed>``.
"""
from __future__ import annotations

import array
import os
import random
import struct
import subprocess
import sys
import tracemalloc
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CompressedImage, Image, Imu, PointCloud2, PointField
from std_msgs.msg import Header, String

from baglib.format import cdr_read
from baglib.format.cdr_fast import serialize
from baglib.format.cdr_read import deserialize
from cdr_reference import ENCAPSULATION, reference

SEED = int(os.environ.get("CDR_READ_SEED") or random.SystemRandom().randrange(2**32))
CASES = 150
TYPE_NAMES = {Image: "sensor_msgs/msg/Image", PointCloud2: "sensor_msgs/msg/PointCloud2",
              CompressedImage: "sensor_msgs/msg/CompressedImage", String: "std_msgs/msg/String"}
ALPHABET = "abcxyz_019/ üé相✓"


# --- random messages -------------------------------------------------------------------------------


def text(rng: random.Random) -> str:
    """0 to 11 characters, some of them 2 or 3 bytes in UTF-8: odd and even byte lengths alike."""
    return "".join(rng.choice(ALPHABET) for _ in range(rng.randrange(12)))


def octets(rng: random.Random, most: int) -> bytes:
    return rng.randbytes(rng.choice([0, 1, 2, 3, rng.randrange(most + 1)]))


def header(rng: random.Random) -> Header:
    msg = Header(frame_id=text(rng))
    msg.stamp.sec = rng.randrange(-2**31, 2**31)
    msg.stamp.nanosec = rng.randrange(2**32)
    return msg


def random_image(rng: random.Random) -> Image:
    return Image(header=header(rng), height=rng.randrange(2**32), width=rng.randrange(9), encoding=text(rng),
                 is_bigendian=rng.randrange(256), step=rng.randrange(2**32), data=octets(rng, 500))


def random_cloud(rng: random.Random) -> PointCloud2:
    fields = [PointField(name=text(rng), offset=rng.randrange(2**32), datatype=rng.randrange(256),
                         count=rng.randrange(2**32)) for _ in range(rng.randrange(6))]
    return PointCloud2(header=header(rng), height=rng.randrange(2**32), width=rng.randrange(2**32), fields=fields,
                       is_bigendian=rng.random() < 0.5, point_step=rng.randrange(2**32),
                       row_step=rng.randrange(2**32), data=octets(rng, 500), is_dense=rng.random() < 0.5)


def random_compressed(rng: random.Random) -> CompressedImage:
    return CompressedImage(header=header(rng), format=text(rng), data=octets(rng, 500))


RANDOM = {Image: random_image, PointCloud2: random_cloud, CompressedImage: random_compressed}


def seeded(what: str) -> random.Random:
    """The generator of one random input, from SEED; its name is printed (pytest shows it when the test fails)."""
    print(f"CDR_READ_SEED={SEED} replays {what}")
    return random.Random(f"{SEED}/{what}")


def random_message(cls: type, case: int) -> Any:
    return RANDOM[cls](seeded(f"{cls.__name__}/{case}"))


def inputs(msg: Any) -> Iterator[tuple[str, bytes | bytearray | memoryview]]:
    """The ways one message reaches the deserializer."""
    little, _ = reference(msg, "<")
    big, _ = reference(msg, ">")
    yield "little endian", little
    yield "big endian", big
    yield "rclpy's bytes (garbage padding)", serialize_message(msg)
    yield "RTPS padding after the message", little + b"\x00" * (-len(little) % 4 or 4)
    yield "options bytes set", little[:2] + b"\x12\x34" + little[4:]
    yield "bytearray", bytearray(big)
    yield "view at an odd offset of a larger buffer", memoryview(b"\xff" * 3 + little + b"\xff")[3:-1]
    yield "signed-char view", memoryview(bytearray(little)).cast("b")


# --- comparing with rclpy ----------------------------------------------------------------------------


def assert_same_types(got: Any, expected: Any, path: str = "msg") -> None:
    """Every field has the type rclpy's field has, recursively (arrays: the same typecode too)."""
    assert type(got) is type(expected), path
    assert got._check_fields == expected._check_fields, path
    for name in expected.get_fields_and_field_types():
        mine, theirs = getattr(got, name), getattr(expected, name)
        assert type(mine) is type(theirs), f"{path}.{name}: {type(mine)} vs {type(theirs)}"
        if isinstance(theirs, array.array):
            assert mine.typecode == theirs.typecode, f"{path}.{name}"
        elif isinstance(theirs, list):
            assert len(mine) == len(theirs), f"{path}.{name}"
            for index, (element, other) in enumerate(zip(mine, theirs)):
                assert_same_types(element, other, f"{path}.{name}[{index}]")
        elif hasattr(theirs, "get_fields_and_field_types"):
            assert_same_types(mine, theirs, f"{path}.{name}")


def masked(data: bytes, padding: list[int]) -> bytes:
    cleared = bytearray(data)
    for position in padding:
        cleared[position] = 0
    return bytes(cleared)


def check_against_rclpy(raw: bytes | bytearray | memoryview, cls: type) -> Any:
    """Decode with both; same types, equal, and re-serialized to the (little-endian) message bytes."""
    expected = deserialize_message(bytes(raw), cls)
    got = deserialize(raw, cls)
    assert_same_types(got, expected)
    assert got == expected
    little, padding = reference(expected, "<")
    assert serialize(got) == little  # cdr_fast writes zero padding, as the reference does
    assert masked(serialize_message(got), padding) == little
    return got


@pytest.mark.parametrize("cls", RANDOM, ids=lambda cls: cls.__name__)
def test_random_messages_decode_like_rclpy(cls: type, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cdr_read, "deserialize_message", refuse)  # the fast path only
    for case in range(CASES):
        msg = random_message(cls, case)
        for how, raw in inputs(msg):
            try:
                got = check_against_rclpy(raw, cls)
            except AssertionError as error:
                raise AssertionError(f"case {case}, {how}: {error}") from error
            if "\x00" not in msg.header.frame_id:
                assert got == msg, (case, how)


def refuse(*_: Any) -> None:
    raise AssertionError("deserialize_message was called on the fast path")


@pytest.mark.parametrize("cls", RANDOM, ids=lambda cls: cls.__name__)
def test_big_payload_is_copied_once_and_owned(cls: type) -> None:
    """A 1080p image's worth of payload: equal to rclpy's, one copy, independent of the input buffer."""
    msg = random_message(cls, 0)
    msg.data = seeded("big payload").randbytes(1920 * 1080 * 3)
    raw = bytearray(bytes(serialize(msg)))
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        before, _ = tracemalloc.get_traced_memory()
        got = deserialize(raw, cls)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(msg.data) <= peak - before < 1.1 * len(msg.data)  # a second copy would double it
    assert got == msg == deserialize_message(bytes(raw), cls)
    raw[-len(msg.data) // 2] ^= 0xFF  # the message owns its data: the input may be reused
    assert got == msg


# --- hand-made wire forms ------------------------------------------------------------------------------


class Wire:
    """Raw CDR fields in one byte order, aligned relative to the end of the encapsulation header."""

    def __init__(self, byte_order: str = "<", encapsulation: bytes | None = None) -> None:
        self.byte_order = byte_order
        self.data = bytearray(ENCAPSULATION[byte_order] if encapsulation is None else encapsulation)

    def u8(self, value: int) -> Wire:
        self.data.append(value)
        return self

    def u32(self, value: int, fmt: str = "I") -> Wire:
        self.data += b"\xee" * (-len(self.data) % 4)  # padding content must not matter
        self.data += struct.pack(self.byte_order + fmt, value)
        return self

    def string(self, raw: bytes, count: int | None = None) -> Wire:
        """A string as its count and raw bytes (whatever they are: no NUL added)."""
        self.u32(len(raw) if count is None else count)
        self.data += raw
        return self

    def header(self, frame_id: bytes = b"cam\x00") -> Wire:
        return self.u32(-5, "i").u32(7).string(frame_id)

    def octets(self, raw: bytes, count: int | None = None) -> Wire:
        return self.string(raw, count)


STRINGS = [b"", b"\x00", b"jpeg\x00", b"jpeg", b"jp\x00eg\x00", b"\x00jpeg\x00", b"\xff\xfeok\x00", b"\xc3",
           b"\xed\xa0\x80\x00", "相机".encode(), b"a" * 7]


@pytest.mark.parametrize("byte_order", "<>")
@pytest.mark.parametrize("raw", STRINGS, ids=repr)
def test_strings_on_the_wire(raw: bytes, byte_order: str) -> None:
    """Count 0, missing or embedded NULs and invalid UTF-8 read as rclpy reads them, in any field."""
    check_against_rclpy(Wire(byte_order).header(raw).string(raw).octets(b"xyz").data, CompressedImage)
    image = Wire(byte_order).header(raw).u32(2).u32(1).string(raw).u8(0).u32(2).octets(b"ab").data
    check_against_rclpy(image, Image)
    cloud = (Wire(byte_order).header(raw).u32(1).u32(1).u32(1).string(raw).u32(0).u8(7).u32(1)
             .u8(0).u32(1).u32(1).octets(b"\x01").u8(1).data)
    check_against_rclpy(cloud, PointCloud2)


@pytest.mark.parametrize("value", [0, 1, 2, 0x80, 0xFF])
def test_bool_bytes(value: int) -> None:
    """rmw_fastrtps reads any non-zero byte as true."""
    cloud = (Wire().header().u32(1).u32(1).u32(0).u8(value).u32(1).u32(1).octets(b"\x01").u8(value).data)
    got = check_against_rclpy(cloud, PointCloud2)
    assert got.is_bigendian is got.is_dense is (value != 0)


@pytest.mark.parametrize("kind", [0x02, 0x03, 0x06, 0x07, 0x08, 0x09, 0x0A, 0x0B])
def test_other_encapsulations_go_to_rclpy(kind: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Parameter-list and XCDR2 encapsulations are rclpy's business: whatever it does, we do."""
    calls: list[bytes] = []

    def spy(data: bytes, cls: type) -> Any:
        calls.append(data)
        return deserialize_message(data, cls)

    monkeypatch.setattr(cdr_read, "deserialize_message", spy)
    message = random_compressed(seeded(f"encapsulation {kind:#04x}"))
    raw = bytes([0, kind]) + reference(message, "<" if kind & 1 else ">")[0][2:]
    try:
        expected: Any = deserialize_message(raw, CompressedImage)
    except RuntimeError:
        with pytest.raises(ValueError, match="CompressedImage"):
            deserialize(memoryview(raw), CompressedImage)
    else:
        assert deserialize(memoryview(raw), CompressedImage) == expected
    assert calls == [raw]


# --- malformed input ----------------------------------------------------------------------------------


def assert_refused(raw: bytes, cls: type, match: str = "") -> None:
    """rclpy rejects it too (so we are not stricter), and ours says which type and what."""
    with pytest.raises(RuntimeError):
        deserialize_message(raw, cls)
    with pytest.raises(ValueError, match=f"malformed {TYPE_NAMES.get(cls, cls.__name__)}.*{match}"):
        deserialize(raw, cls)


@pytest.mark.parametrize("byte_order", "<>")
@pytest.mark.parametrize("cls", RANDOM, ids=lambda cls: cls.__name__)
def test_every_truncation_is_refused(cls: type, byte_order: str) -> None:
    for case in range(3):
        raw, _ = reference(random_message(cls, case), byte_order)
        for cut in range(len(raw)):
            assert_refused(raw[:cut], cls)


LIES: list[tuple[str, type, Callable[[], bytearray], str]] = [
    ("data count past the end", Image,
     lambda: Wire().header().u32(1).u32(1).string(b"rgb8\x00").u8(0).u32(3).octets(b"abc", 2**32 - 1).data,
     "data needs 4294967295 bytes"),
    ("frame_id count past the end", CompressedImage,
     lambda: Wire().u32(-5, "i").u32(7).string(b"cam\x00", 2**20).data, "header.frame_id needs 1048576 bytes"),
    ("format count past the end", CompressedImage,
     lambda: Wire().header().string(b"jpeg\x00", 2**31).octets(b"").data, "format needs 2147483648 bytes"),
    ("fields count past the end", PointCloud2,
     lambda: Wire().header().u32(1).u32(1).u32(2**32 - 1).string(b"x\x00").u32(0).u8(7).u32(1).data,
     "fields counts 4294967295 elements"),
    ("a field more than there is", PointCloud2,
     lambda: Wire().header().u32(1).u32(1).u32(2).string(b"x\x00").u32(0).u8(7).u32(1).u8(0).u32(1).u32(1)
     .octets(b"\x01").u8(1).data, "fields"),
    ("unknown encapsulation kind", CompressedImage,
     lambda: Wire(encapsulation=b"\x00\x05\x00\x00").header().string(b"png\x00").octets(b"").data, "rclpy"),
    ("encapsulation's first byte not zero", CompressedImage,
     lambda: Wire(encapsulation=b"\x01\x01\x00\x00").header().string(b"png\x00").octets(b"").data, "rclpy"),
    ("half an encapsulation header", Image, lambda: bytearray(b"\x00\x01"), "2 bytes"),
    ("nothing", PointCloud2, lambda: bytearray(), "0 bytes"),
    ("a truncated String (the fallback)", String, lambda: Wire().string(b"hello\x00").data[:-2], "rclpy"),
]


@pytest.mark.parametrize(("cls", "make", "match"), [lie[1:] for lie in LIES], ids=[lie[0] for lie in LIES])
def test_lengths_and_headers_that_lie_are_refused(cls: type, make: Callable[[], bytearray], match: str) -> None:
    assert_refused(bytes(make()), cls, match)


def test_input_buffer_is_released_even_on_error() -> None:
    """A player may reuse (resize) its read buffer: no view of it survives, not even in a traceback."""
    raw = bytearray(reference(random_message(Image, 0), "<")[0])
    deserialize(raw, Image)
    raw += b"\x00"
    del raw[20:]
    with pytest.raises(ValueError) as caught:
        deserialize(raw, Image)
    raw += b"\x00"
    assert caught.value.__traceback__ is not None


def test_with_field_checks_on() -> None:
    """With ROS_PYTHON_CHECK_FIELDS=1 (read when the message modules load) every setter validates."""
    script = (
        "import random, sys\n"
        "sys.path[:0] = sys.argv[1:]\n"
        "import test_cdr_read as t\n"
        "for cls in t.RANDOM:\n"
        "    for case in range(20):\n"
        "        for _, raw in t.inputs(t.random_message(cls, case)):\n"
        "            assert t.check_against_rclpy(raw, cls)._check_fields is True\n"
    )
    here = os.path.dirname(__file__)
    subprocess.run([sys.executable, "-c", script, here, os.path.dirname(here)], check=True, timeout=120,
                   env={**os.environ, "ROS_PYTHON_CHECK_FIELDS": "1", "CDR_READ_SEED": str(SEED)})


# --- other types ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("msg", [String(data="hello ✓"), Imu(), PointField(name="x", count=1)], ids=repr)
def test_other_types_use_rclpy(msg: Any) -> None:
    raw = serialize_message(msg)
    for given in (raw, memoryview(raw), bytearray(raw)):
        got = deserialize(given, type(msg))
        assert got == msg and type(got) is type(msg)
