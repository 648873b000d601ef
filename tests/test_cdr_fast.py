"""The copy-free CDR serializer against rclpy's ``serialize_message``.

Fast-CDR (behind rclpy) leaves alignment padding uninitialized: the same message serialized twice can
differ in its padding bytes (checked below). So identity is proven three ways for every variation:

* byte for byte against an independent reference encoder (``cdr_reference.py``) from the message
  introspection (``get_fields_and_field_types``), which also reports where the padding is and
  writes it as zeros, like the fast path must;
* byte for byte against rclpy's bytes of many serializations, everywhere except at those padding
  positions (and nowhere else do they differ);
* by decoding: rclpy's ``deserialize_message`` of the fast bytes equals the original message, and
  rosbags' Jazzy typestore decodes rclpy's bytes and the fast bytes to the same fields.
"""
from __future__ import annotations

import array
import itertools
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu, PointCloud2, PointField, Temperature
from std_msgs.msg import String

from baglib.format import cdr_fast
from baglib.write.writer import BagWriter
from baglib.format.cdr_fast import MIN_BUFFERS_SIZE, SerializedBuffers, serialize
from baglib.format.cdr_size import serialized_size
from baglib.format.message_definitions import type_hash
from baglib.format.metadata import TopicInfo
from cdr_reference import reference

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
RCLPY_RUNS = 8
FRAME_IDS = ["", "a", "ab", "cam", "base", "lidar", "camera", "optical", "imu_link", "camera_01", "kamera_ü",
             "相机", "nul\x00tail"]


# --- message variations --------------------------------------------------------------------------


def payload(size: int, seed: int) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()


def images() -> list[Image]:
    out = []
    encodings = ["", "8UC1", "mono8", "rgb8", "bgra8", "16UC1", "bayer_rggb8", "yuv422_yuy2"]
    shapes = [(0, 0, 0), (1, 1, 1), (3, 5, 15), (7, 3, 11), (2, 13, 40), (1, 3, 3)]
    for n, (frame_id, encoding, (height, width, step), big_endian) in enumerate(
            itertools.product(FRAME_IDS, encodings, shapes, (0, 1))):
        if n % 3:  # a third of the product still covers every frame_id/encoding/shape pair
            continue
        image = Image(height=height, width=width, encoding=encoding, is_bigendian=big_endian, step=step)
        image.header.frame_id = frame_id
        image.header.stamp.sec = -n if n % 2 else 2**31 - 1 - n
        image.header.stamp.nanosec = (n * 7919) % 1_000_000_000
        image.data = payload(height * step, n)
        out.append(image)
    big = Image(height=1080, width=1920, encoding="rgb8", step=1920 * 3)
    big.header.frame_id = "camera_optical_frame"
    big.data = payload(1080 * 1920 * 3, 1)
    odd = Image(height=MIN_BUFFERS_SIZE, width=1, encoding="mono8", step=1)  # exactly the threshold
    odd.data = payload(MIN_BUFFERS_SIZE, 2)
    below = Image(height=MIN_BUFFERS_SIZE - 1, width=1, encoding="mono8", step=1)
    below.data = payload(MIN_BUFFERS_SIZE - 1, 3)
    return [*out, big, odd, below]


FIELD_NAMES = ["", "x", "yz", "rgb", "ring", "range", "intens", "t_offset", "reflectivity"]


def clouds() -> list[PointCloud2]:
    out = []
    for n, (frame_id, field_count, dense, big_endian, points) in enumerate(
            itertools.product(FRAME_IDS, range(6), (False, True), (False, True), (0, 1, 3, 7))):
        if n % 4:
            continue
        fields = [PointField(name=FIELD_NAMES[(n + k) % len(FIELD_NAMES)], offset=4 * k,
                             datatype=1 + (n + k) % 8, count=1 + (k % 3)) for k in range(field_count)]
        point_step = 4 * field_count + (n % 3)
        cloud = PointCloud2(height=1, width=points, fields=fields, is_bigendian=big_endian,
                            point_step=point_step, row_step=point_step * points, is_dense=dense)
        cloud.header.frame_id = frame_id
        cloud.header.stamp.sec = n
        cloud.header.stamp.nanosec = 999_999_999 - n
        cloud.data = payload(point_step * points, n)
        out.append(cloud)
    for dense in (False, True):  # the lidar's size: 131072 points, 24 bytes each
        big = PointCloud2(height=64, width=2048, point_step=24, row_step=24 * 2048, is_dense=dense)
        big.header.frame_id = "lidar"
        big.fields = [PointField(name=name, offset=4 * k, datatype=PointField.FLOAT32, count=1)
                      for k, name in enumerate(["x", "y", "z", "intensity", "t", "ring"])]
        big.data = payload(24 * 131072, 7)
        out.append(big)
    return out


def compressed_images() -> list[CompressedImage]:
    out = []
    formats = ["", "jpeg", "png", "rgb8; jpeg compressed bgr8", "16UC1; compressedDepth png", "qoi"]
    for n, (frame_id, fmt, size) in enumerate(itertools.product(FRAME_IDS, formats, (0, 1, 2, 3, 5, 1000))):
        if n % 2:
            continue
        image = CompressedImage(format=fmt)
        image.header.frame_id = frame_id
        image.header.stamp.sec = n
        image.data = payload(size, n)
        out.append(image)
    big = CompressedImage(format="jpeg")
    big.header.frame_id = "camera"
    big.data = payload(300_000, 9)
    return [*out, big]


def imus() -> list[Imu]:
    """Every frame_id (each puts the doubles at another offset before their 8-alignment), covariances given
    as tuples, lists and float64 arrays, extreme values."""
    rng = np.random.default_rng(0x1A)
    extremes = [0.0, -0.0, 1e-308, -1.7976931348623157e308, float("inf"), float("-inf"), 2.0 ** 53 + 1]
    out = []
    for n, frame_id in enumerate(FRAME_IDS * 3):
        values = rng.normal(0.0, 10.0 ** (n % 7 - 3), 37).tolist()
        values[n % 37] = extremes[n % len(extremes)]
        shape = (tuple, list, np.array)[n % 3]
        imu = Imu()
        imu.header.frame_id = frame_id
        imu.header.stamp.sec = -n if n % 2 else 2**31 - 1 - n
        imu.header.stamp.nanosec = (n * 104729) % 1_000_000_000
        imu.orientation.x, imu.orientation.y, imu.orientation.z, imu.orientation.w = values[0:4]
        imu.orientation_covariance = shape(values[4:13])
        imu.angular_velocity.x, imu.angular_velocity.y, imu.angular_velocity.z = values[13:16]
        imu.angular_velocity_covariance = shape(values[16:25])
        imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z = values[25:28]
        imu.linear_acceleration_covariance = shape(values[28:37])
        out.append(imu)
    return out


def camera_infos() -> list[CameraInfo]:
    """Every frame_id and distortion model length (the string ends at another offset each time), ``d`` empty
    and of 1, 5, 8 and 14 values, k/r/p given as an array, a tuple and a list, roi flags."""
    rng = np.random.default_rng(0xCA)
    models = ["", "plumb_bob", "rational_polynomial", "equidistant", "x"]
    out = []
    for n, (frame_id, model, d_size) in enumerate(itertools.product(FRAME_IDS, models, (0, 1, 5, 8, 14))):
        if n % 3:
            continue
        info = CameraInfo(height=n * 7 % 4096, width=n * 13 % 8192, distortion_model=model,
                          d=rng.normal(0.0, 1.0, d_size).tolist(), binning_x=n % 4, binning_y=n % 3)
        info.header.frame_id = frame_id
        info.header.stamp.sec = n
        info.header.stamp.nanosec = (n * 7919) % 1_000_000_000
        info.k = rng.normal(500.0, 100.0, 9)
        info.r = tuple(rng.normal(0.0, 1.0, 9).tolist())
        info.p = rng.normal(0.0, 300.0, 12).tolist()
        info.roi.x_offset, info.roi.y_offset, info.roi.height, info.roi.width = n, n + 1, n % 480, n % 640
        info.roi.do_rectify = bool(n % 2)
        out.append(info)
    return out


MESSAGES = [*images(), *clouds(), *compressed_images(), *imus(), *camera_infos()]
TYPE_NAMES = {Image: "sensor_msgs/msg/Image", PointCloud2: "sensor_msgs/msg/PointCloud2",
              CompressedImage: "sensor_msgs/msg/CompressedImage", Imu: "sensor_msgs/msg/Imu",
              CameraInfo: "sensor_msgs/msg/CameraInfo"}


def describe(msg: Any) -> str:
    size = f"{len(msg.data)} B" if hasattr(msg, "data") else "fixed"
    return f"{type(msg).__name__}[{msg.header.frame_id!r}, {size}]"


#: The variations by type: one test per type goes through all of its variations (a test per variation made
#: some 2600 tests, whose per-test overhead under pytest-xdist cost more than the checks). Every failure names
#: the variation (``describe`` and its index).
BY_TYPE = {cls.__name__: [msg for msg in MESSAGES if type(msg) is cls] for cls in TYPE_NAMES}


# --- identity --------------------------------------------------------------------------------------


def test_rclpy_leaves_padding_uninitialized_and_only_padding_differs() -> None:
    """Fast-CDR's padding bytes are garbage here, which is why the comparisons below mask them."""
    garbage = 0
    for msg in MESSAGES[:: max(1, len(MESSAGES) // 60)]:
        fast = bytes(serialize(msg))
        _, padding = reference(msg)
        for _ in range(RCLPY_RUNS):
            expected = serialize_message(msg)
            assert len(expected) == len(fast)
            differ = {i for i in range(len(fast)) if fast[i] != expected[i]}
            assert differ <= set(padding), (describe(msg), sorted(differ - set(padding)))
            garbage += len(differ)
    assert garbage > 0  # if this ever fails, rclpy zeroes padding and plain equality would do


@pytest.mark.parametrize("type_name", list(BY_TYPE))
def test_byte_identical_except_rclpy_padding(type_name: str) -> None:
    assert len(BY_TYPE[type_name]) > 10
    for index, msg in enumerate(BY_TYPE[type_name]):
        where = f"{describe(msg)} (variation {index})"
        result = serialize(msg)
        fast = bytes(result)
        expected, padding = reference(msg)
        assert fast == expected, where  # exact, padding included (zeros)
        assert all(fast[i] == 0 for i in padding), where
        mask = np.ones(len(fast), dtype=bool)
        mask[padding] = False
        for _ in range(3):
            from_rclpy = np.frombuffer(serialize_message(msg), dtype=np.uint8)
            assert len(from_rclpy) == len(fast), where
            assert np.array_equal(from_rclpy[mask], np.frombuffer(fast, dtype=np.uint8)[mask]), where
        if len(getattr(msg, "data", ())) >= MIN_BUFFERS_SIZE:
            assert isinstance(result, SerializedBuffers) and len(result) == len(fast), where
        else:
            assert isinstance(result, bytes), where


@pytest.mark.parametrize("type_name", list(BY_TYPE))
def test_decodes_back_to_the_message(type_name: str) -> None:
    for index, msg in enumerate(BY_TYPE[type_name]):
        fast = bytes(serialize(msg))
        decoded = deserialize_message(fast, type(msg))
        if "\x00" in msg.header.frame_id:
            assert decoded.header.frame_id == msg.header.frame_id.split("\x00")[0]
            decoded.header.frame_id = msg.header.frame_id
        assert decoded == msg, f"{describe(msg)} (variation {index})"


def fields(type_name: str, msg: Any) -> tuple:
    """rosbags' decoded message as plain values."""
    header = (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id)
    if type_name == "sensor_msgs/msg/CameraInfo":
        roi = msg.roi
        return (header, msg.height, msg.width, msg.distortion_model, np.asarray(msg.d, dtype=np.float64).tobytes(),
                np.concatenate([msg.k, msg.r, msg.p]).tobytes(), msg.binning_x, msg.binning_y,
                (roi.x_offset, roi.y_offset, roi.height, roi.width, bool(roi.do_rectify)))
    if type_name == "sensor_msgs/msg/Imu":
        return header, np.concatenate([
            [msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w], msg.orientation_covariance,
            [msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z], msg.angular_velocity_covariance,
            [msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z],
            msg.linear_acceleration_covariance]).tobytes()
    data = np.asarray(msg.data).tobytes()
    if type_name == "sensor_msgs/msg/Image":
        return header, msg.height, msg.width, msg.encoding, msg.is_bigendian, msg.step, data
    if type_name == "sensor_msgs/msg/PointCloud2":
        return (header, msg.height, msg.width, [(f.name, f.offset, f.datatype, f.count) for f in msg.fields],
                msg.is_bigendian, msg.point_step, msg.row_step, data, msg.is_dense)
    return header, msg.format, data


@pytest.mark.parametrize("name", list(BY_TYPE))
def test_rosbags_decodes_both_alike(name: str) -> None:
    for index, msg in enumerate(MESSAGES[::3]):  # every third variation, as before by type
        if type(msg).__name__ != name:
            continue
        where = f"{describe(msg)} (variation {index * 3} of all)"
        type_name = TYPE_NAMES[type(msg)]
        fast = fields(type_name, TYPESTORE.deserialize_cdr(bytes(serialize(msg)), type_name))
        assert fast == fields(type_name, TYPESTORE.deserialize_cdr(serialize_message(msg), type_name)), where
        if type_name in ("sensor_msgs/msg/Imu", "sensor_msgs/msg/CameraInfo"):
            continue
        assert fast[-1 if type_name != "sensor_msgs/msg/PointCloud2" else -2] == bytes(msg.data), where
        if type_name == "sensor_msgs/msg/PointCloud2":
            assert fast[3] == [(f.name, f.offset, f.datatype, f.count) for f in msg.fields], where


# --- buffers, fallbacks ----------------------------------------------------------------------------


def test_big_payload_is_a_view_of_msg_data() -> None:
    image = images()[-3]
    result = serialize(image)
    assert isinstance(result, SerializedBuffers)
    prefix, view = result.buffers
    assert isinstance(prefix, bytes) and isinstance(view, memoryview)
    assert view.obj is image.data and view.nbytes == len(image.data)  # no copy of the pixels
    assert len(result) == len(prefix) + len(image.data) == len(serialize_message(image))
    assert list(result) == [prefix, view] and "bytes in 2 buffers" in repr(result)
    cloud = clouds()[-1]
    prefix, view, suffix = serialize(cloud).buffers  # type: ignore[union-attr]
    assert view.obj is cloud.data and suffix == b"\x01"


def test_imu_covariance_put_behind_the_setter() -> None:
    """A list in the slot (rclpy's serializer crashes the process on it) is packed value by value."""
    imu = Imu()
    imu._angular_velocity_covariance = [0.5] * 9
    assert serialize(imu) == reference(imu)[0]
    imu._angular_velocity_covariance = [0.5] * 8
    with pytest.raises(struct.error):
        serialize(imu)


def test_data_sources() -> None:
    """``data`` assigned as bytes, list, array or numpy ends up an array.array('B') either way."""
    for data in (b"\x01\x02\x03", [1, 2, 3], array.array("B", [1, 2, 3]), bytearray(b"\x01\x02\x03"),
                 np.array([1, 2, 3], dtype=np.uint8)):
        image = Image(height=1, width=3, encoding="mono8", step=3, data=data)
        assert bytes(serialize(image)) == reference(image)[0]


def test_non_buffer_data_falls_back(monkeypatch: pytest.MonkeyPatch) -> None:
    """rclpy serializes it; the result is still exact (cut to size, padding zeroed)."""
    calls: list[Any] = []

    def spy(msg: Any) -> bytes:
        calls.append(msg)
        return serialize_message(msg)

    monkeypatch.setattr(cdr_fast, "serialize_message", spy)
    image = Image(encoding="mono8")
    image._data = [1, 2, 3]  # bypassing the setter: not a buffer
    assert serialize(image) == reference(image)[0] and calls == [image]



@pytest.mark.parametrize("msg", [String(data="hello ✓"), Temperature(), PointField(name="x", count=1)], ids=repr)
def test_other_types_use_rclpy(msg: Any) -> None:
    result = serialize(msg)
    assert isinstance(result, bytes)
    assert deserialize_message(result, type(msg)) == msg
    assert len(result) == serialized_size(msg) <= len(serialize_message(msg))


# --- through the bag writer ------------------------------------------------------------------------


@pytest.mark.parametrize(("storage_id", "preset"), [("mcap", ""), ("mcap", "fastwrite"), ("mcap", "zstd_fast"),
                                                    ("mcap", "zstd_small"), ("sqlite3", "")])
def test_buffers_recorded_and_read_back(tmp_path: Path, storage_id: str, preset: str) -> None:
    """SerializedBuffers and bytes, big and small, interleaved, land in the bag as the exact CDR."""
    plan = [*images()[-3:], images()[5], clouds()[-1], compressed_images()[-1], clouds()[3], images()[-3]]
    bag = tmp_path / "bag"
    with BagWriter(bag, storage_id=storage_id, storage_preset_profile=preset) as writer:
        for type_name in TYPE_NAMES.values():
            writer.add_topic(TopicInfo("/" + type_name.rsplit("/", 1)[1], type_name,
                                       type_description_hash=type_hash(type_name)))
        for n, msg in enumerate(plan):
            writer.write("/" + type(msg).__name__, serialize(msg), 1000 + n, 1000 + n)  # type: ignore[arg-type]
    expected = [(1000 + n, "/" + type(msg).__name__, bytes(serialize(msg))) for n, msg in enumerate(plan)]
    with Reader(bag) as reader:
        got = sorted((t, c.topic, bytes(raw)) for c, t, raw in reader.messages())
    assert got == expected
    if storage_id == "mcap":
        with open(next(bag.glob("*.mcap")), "rb") as file:
            read = sorted((m.log_time, c.topic, m.data) for _, c, m in make_reader(file).iter_messages())
        assert read == expected
