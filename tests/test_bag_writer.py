"""The bag writer against real readers: every bag is read back with ``rosbags`` and, for MCAP, with
the ``mcap`` reader plus ``mcap-ros2-support``; messages are real rclpy-serialized messages and
every one of them is decoded and compared field by field.
"""
from __future__ import annotations

import errno
import functools
import json
import os
import re
import sqlite3
import struct
import subprocess
import sys
import textwrap
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
import yaml
import zstandard
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from rclpy.duration import Infinite
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from rosbags.interfaces import MessageDefinitionFormat
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from sensor_msgs.msg import Image, Imu, PointCloud2, PointField
from std_msgs.msg import String

from baglib.format import cdr_fast, message_definitions
from baglib.write import mcap_storage
from baglib.write.writer import BagExistsError, BagWriteError, BagWriter
from baglib.format.cdr_fast import SerializedBuffers
from baglib.write.direct_file import GATHER, DirectFile
from baglib.format.mcap_records import scan
from baglib.write.mcap_storage import DEFAULT_CHUNK_SIZE, PADDING_OPCODE, McapStorage
from baglib.read.reader import BagReader
from baglib.format.message_definitions import (
    MessageDefinitionNotFoundError,
    message_definition,
    type_hash,
)
from baglib.format.metadata import QOS_KEYS, TopicInfo, qos_profile_dict

T0 = 1_718_000_000_000_000_000
REPO = Path(__file__).resolve().parent.parent
SENSOR_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE, deadline=Infinite, lifespan=Infinite,
    liveliness=LivelinessPolicy.AUTOMATIC, liveliness_lease_duration=Infinite,
)


# --- messages ---------------------------------------------------------------------------------


def make_string(i: int) -> String:
    return String(data=f"hello {i} ✓")


def make_image(i: int) -> Image:
    image = Image(height=480, width=640, encoding="rgb8", step=640 * 3)
    image.header.frame_id = "camera"
    image.header.stamp.sec = 100 + i
    image.data = (np.arange(640 * 480 * 3, dtype=np.uint32) * (i + 7) % 251).astype(np.uint8).tobytes()
    return image


def make_cloud(i: int) -> PointCloud2:
    points = np.random.default_rng(i).random((1000, 3), dtype=np.float32)
    cloud = PointCloud2(height=1, width=1000, point_step=12, row_step=12000, is_dense=True)
    cloud.header.frame_id = "lidar"
    cloud.fields = [
        PointField(name=name, offset=4 * index, datatype=PointField.FLOAT32, count=1)
        for index, name in enumerate("xyz")
    ]
    cloud.data = points.tobytes()
    return cloud


def make_imu(i: int) -> Imu:
    imu = Imu()
    imu.header.frame_id = "imu"
    imu.header.stamp.sec = 5
    imu.header.stamp.nanosec = i
    imu.orientation.w = 1.0 - i / 100
    imu.angular_velocity.z = 0.25 * i
    imu.linear_acceleration.x = 9.81
    imu.orientation_covariance = [float(i)] * 9
    return imu


TOPICS = {
    "/chatter": ("std_msgs/msg/String", make_string),
    "/camera/image_raw": ("sensor_msgs/msg/Image", make_image),
    "/points": ("sensor_msgs/msg/PointCloud2", make_cloud),
    "/imu": ("sensor_msgs/msg/Imu", make_imu),
}


def as_bytes(value: Any) -> bytes:
    return value.tobytes() if isinstance(value, np.ndarray) else bytes(value)


def message_fields(type_name: str, msg: Any) -> tuple:
    """The values compared between what was written and what a reader decoded."""
    if type_name == "std_msgs/msg/String":
        return (msg.data,)
    if type_name == "sensor_msgs/msg/Image":
        return (msg.header.frame_id, msg.header.stamp.sec, msg.height, msg.width, msg.encoding,
                msg.step, as_bytes(msg.data))
    if type_name == "sensor_msgs/msg/PointCloud2":
        return (msg.header.frame_id, msg.width, msg.point_step, msg.row_step,
                [(f.name, f.offset, f.datatype) for f in msg.fields], as_bytes(msg.data))
    return (msg.header.frame_id, msg.header.stamp.nanosec, msg.orientation.w, msg.angular_velocity.z,
            msg.linear_acceleration.x, [float(x) for x in msg.orientation_covariance])


@dataclass
class Written:
    topic: str
    type: str
    log_time: int
    publish_time: int
    fields: tuple


def topic_info(name: str, qos: QoSProfile | None = None) -> TopicInfo:
    return TopicInfo(name, TOPICS[name][0], offered_qos_profiles=[qos_profile_dict(qos or SENSOR_QOS)],
                     type_description_hash=type_hash(TOPICS[name][0]))


def write_messages(
    writer: BagWriter, plan: list[tuple[str, int]], start: int = T0, step: int = 10_000_000,
    wrap: type = bytes,
) -> list[Written]:
    """Write (topic, index) pairs at ``step`` ns apart; return what was written."""
    written = []
    for n, (topic, i) in enumerate(plan):
        type_name, make = TOPICS[topic]
        msg = make(i)
        log_time = start + n * step
        writer.write(topic, wrap(serialize_message(msg)), log_time, log_time - 1234)
        written.append(Written(topic, type_name, log_time, log_time - 1234, message_fields(type_name, msg)))
    return written


def mixed_plan(count: int) -> list[tuple[str, int]]:
    names = list(TOPICS)
    return [(names[n % len(names)], n) for n in range(count)]


# --- readers ----------------------------------------------------------------------------------


@functools.lru_cache(maxsize=None)
def types_from_msg(text: str, name: str) -> dict:
    """rosbags' parse of a definition text (one parse per distinct text: many bags store the same ones)."""
    return get_types_from_msg(text, name)


def read_rosbags(bag: Path) -> list[tuple[str, int, tuple]]:
    """All messages via rosbags' Reader, typed from the bag's own definitions (no typestore)."""
    out = []
    with Reader(bag) as reader:
        store = get_typestore(Stores.EMPTY)
        for connection in reader.connections:
            assert connection.msgdef.format == MessageDefinitionFormat.MSG
            store.register(types_from_msg(connection.msgdef.data, connection.msgtype))
        for connection, timestamp, raw in reader.messages():
            msg = store.deserialize_cdr(raw, connection.msgtype)
            out.append((connection.topic, timestamp, message_fields(connection.msgtype, msg)))
    # AnyReader recomputes every type hash from the stored text and raises on a mismatch.
    with AnyReader([bag]) as anyreader:
        assert sum(1 for _ in anyreader.messages()) == len(out)
    return out


def read_mcap(path: Path) -> list[tuple[str, int, int, int, tuple]]:
    with open(path, "rb") as file:
        reader = make_reader(file, decoder_factories=[DecoderFactory()])
        return [
            (channel.topic, message.log_time, message.publish_time, message.sequence,
             message_fields(schema.name, decoded))
            for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False)
        ]


def load_metadata(bag: Path) -> dict:
    return yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def check_metadata_matches(bag: Path, written: list[Written]) -> dict:
    """metadata.yaml agrees with what was written and with what the files hold."""
    meta = load_metadata(bag)
    assert meta["version"] == 9
    assert meta["message_count"] == len(written)
    times = [w.log_time for w in written]
    assert meta["starting_time"]["nanoseconds_since_epoch"] == min(times)
    assert meta["duration"]["nanoseconds"] == max(times) - min(times)
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    for topic in counts:
        assert counts[topic] == sum(1 for w in written if w.topic == topic)
    assert meta["relative_file_paths"] == [f["path"] for f in meta["files"]]
    assert sum(f["message_count"] for f in meta["files"]) == len(written)
    assert sorted(os.listdir(bag)) == sorted([*meta["relative_file_paths"], "metadata.yaml"])
    return meta


# --- message definitions and QoS --------------------------------------------------------------


def test_message_definition_matches_rosbag2_layout() -> None:
    encoding, text = message_definition("sensor_msgs/msg/Image")
    share = Path(sys.prefix) / "share"
    image = (share / "sensor_msgs/msg/Image.msg").read_text()
    header = (share / "std_msgs/msg/Header.msg").read_text()
    time_ = (share / "builtin_interfaces/msg/Time.msg").read_text()
    separator = "\n" + "=" * 80 + "\n"
    assert encoding == "ros2msg"
    assert text == (f"{image}{separator}MSG: std_msgs/Header\n{header}"
                    f"{separator}MSG: builtin_interfaces/Time\n{time_}")
    string = (share / "std_msgs/msg/String.msg").read_text()
    assert message_definition("std_msgs/String") == ("ros2msg", string)


@pytest.mark.parametrize("type_name", sorted({t for t, _ in TOPICS.values()}))
def test_definition_text_hashes_to_the_type_hash(type_name: str) -> None:
    encoding, text = message_definition(type_name)
    assert encoding == "ros2msg"
    assert text.count("MSG: std_msgs/Header") == (0 if type_name.startswith("std_msgs") else 1)
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(text, type_name))
    assert re.fullmatch(r"RIHS01_[0-9a-f]{64}", type_hash(type_name))
    assert store.hash_rihs01(type_name) == type_hash(type_name)


def test_idl_fallback_when_no_msg_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    msg_dir = tmp_path / "share" / "idl_only_pkg" / "msg"
    msg_dir.mkdir(parents=True)
    (msg_dir / "Inner.idl").write_text(
        "module idl_only_pkg {\n  module msg {\n    struct Inner {\n      int32 value;\n    };\n  };\n};\n"
    )
    (msg_dir / "Outer.idl").write_text(
        '#include "idl_only_pkg/msg/Inner.idl"\n\nmodule idl_only_pkg {\n  module msg {\n'
        "    struct Outer {\n      idl_only_pkg::msg::Inner inner;\n      string name;\n    };\n  };\n};\n"
    )
    monkeypatch.setattr(sys, "prefix", str(tmp_path))
    encoding, text = message_definition("idl_only_pkg/msg/Outer")
    separator = "=" * 80 + "\n"
    assert encoding == "ros2idl"
    assert text.startswith(f"{separator}IDL: idl_only_pkg/msg/Outer\n#include")
    assert f"\n{separator}IDL: idl_only_pkg/msg/Inner\nmodule" in text
    # Split it the way rosbags' AnyReader does; its IDL parser does not understand the #include
    # lines (which rosbag2 writes too and which name the dependencies), so they are dropped here.
    types = {}
    for block in text.split(separator)[1:]:
        header, idl = block.split("\n", 1)
        assert header.startswith("IDL: ")
        types.update(get_types_from_idl(re.sub(r"(?m)^#include .*$", "", idl)))
    assert set(types) == {"idl_only_pkg/msg/Outer", "idl_only_pkg/msg/Inner"}
    with pytest.raises(MessageDefinitionNotFoundError):
        message_definition("idl_only_pkg/msg/Missing")
    message_definitions._share_directories.cache_clear()


def test_qos_profile_dict() -> None:
    profile = qos_profile_dict(SENSOR_QOS)
    assert list(profile) == list(QOS_KEYS)
    assert profile["history"] == "keep_last" and profile["depth"] == 5
    assert profile["reliability"] == "best_effort" and profile["durability"] == "volatile"
    assert profile["liveliness"] == "automatic"
    infinite = {"sec": 9223372036, "nsec": 854775807}
    assert profile["deadline"] == profile["lifespan"] == profile["liveliness_lease_duration"] == infinite
    latched = qos_profile_dict(QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                          history=HistoryPolicy.KEEP_ALL))
    assert latched["durability"] == "transient_local" and latched["history"] == "keep_all"
    assert latched["deadline"] == {"sec": 0, "nsec": 0}
    with pytest.raises(ValueError, match="lacks"):
        TopicInfo("/x", "std_msgs/msg/String", offered_qos_profiles=[{"history": "keep_last"}])


# --- complete bags ----------------------------------------------------------------------------


def test_mcap_bag_reads_back_with_both_readers(tmp_path: Path) -> None:
    bag = tmp_path / "my_bag"
    events: list[tuple[str, str]] = []
    with BagWriter(bag, custom_data={"robot": "r2"}, on_split=lambda a, b: events.append((a, b))) as writer:
        for name in TOPICS:
            writer.add_topic(topic_info(name))
        writer.add_topic(topic_info("/chatter"))  # idempotent
        writer.add_topic(TopicInfo("/never", "std_msgs/msg/String"))  # no messages, no QoS, no hash
        written = write_messages(writer, mixed_plan(12))
        assert writer.topic_message_counts == {"/chatter": 3, "/camera/image_raw": 3, "/points": 3,
                                               "/imu": 3, "/never": 0}
        assert writer.current_file == bag / "my_bag_0.mcap"
    assert events == [(str(bag / "my_bag_0.mcap"), "")]

    meta = check_metadata_matches(bag, written)
    assert meta["storage_identifier"] == "mcap" and meta["ros_distro"] == "jazzy"
    assert meta["custom_data"] == {"robot": "r2"}
    assert meta["relative_file_paths"] == ["my_bag_0.mcap"]
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert topics["/never"]["message_count"] == 0
    assert topics["/never"]["topic_metadata"]["type_description_hash"] == type_hash("std_msgs/msg/String")
    assert topics["/imu"]["topic_metadata"]["offered_qos_profiles"] == [qos_profile_dict(SENSOR_QOS)]

    expected = sorted((w.topic, w.log_time, w.fields) for w in written)
    assert sorted(read_rosbags(bag)) == expected
    from_mcap = read_mcap(bag / "my_bag_0.mcap")
    assert sorted((t, log, f) for t, log, _, _, f in from_mcap) == expected
    assert {(t, log, pub) for t, log, pub, _, _ in from_mcap} == \
        {(w.topic, w.log_time, w.publish_time) for w in written}
    assert sorted(seq for t, _, _, seq, _ in from_mcap if t == "/imu") == [0, 1, 2]

    with open(bag / "my_bag_0.mcap", "rb") as file:
        reader = make_reader(file)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 12
        assert {s.name: s.encoding for s in summary.schemas.values()} == {
            t: "ros2msg" for t in ["std_msgs/msg/String", "sensor_msgs/msg/Image",
                                   "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/Imu"]}
        for schema in summary.schemas.values():
            assert schema.data.decode() == message_definition(schema.name)[1]
        for channel in summary.channels.values():
            assert channel.message_encoding == "cdr"
            assert set(channel.metadata) == {"offered_qos_profiles", "topic_type_hash"}
            topic = topics[channel.topic]["topic_metadata"]
            assert channel.metadata["topic_type_hash"] == topic["type_description_hash"]
            assert yaml.safe_load(channel.metadata["offered_qos_profiles"]) == topic["offered_qos_profiles"]
        assert summary.chunk_indexes and all(c.message_index_offsets for c in summary.chunk_indexes)
        assert [m.name for m in summary.metadata_indexes] == ["rosbag2", "rosbag2"]
        records = [yaml.safe_load(m.metadata["serialized_metadata"]) for m in reader.iter_metadata()]
    assert records[0]["message_count"] == 0 and records[-1]["message_count"] == 12
    assert records[-1]["files"][0]["message_count"] == 12


def test_sqlite_bag_reads_back(tmp_path: Path) -> None:
    bag = tmp_path / "db_bag"
    with BagWriter(bag, storage_id="sqlite3") as writer:
        for name in TOPICS:
            writer.add_topic(topic_info(name))
        writer.add_topic(TopicInfo("/never", "std_msgs/msg/String"))
        # More rows than one insert batch holds.
        plan = mixed_plan(8) + [("/imu" if n % 2 else "/chatter", n) for n in range(2092)]
        written = write_messages(writer, plan)
    meta = check_metadata_matches(bag, written)
    assert meta["storage_identifier"] == "sqlite3"
    assert sorted(os.listdir(bag)) == ["db_bag_0.db3", "metadata.yaml"]  # no -wal / -journal
    assert sorted(read_rosbags(bag)) == sorted((w.topic, w.log_time, w.fields) for w in written)

    db = sqlite3.connect(bag / "db_bag_0.db3")
    assert db.execute("SELECT schema_version, ros_distro FROM schema").fetchall() == [(4, "jazzy")]
    rows = db.execute("SELECT topic_type, encoding, encoded_message_definition, type_description_hash"
                      " FROM message_definitions").fetchall()
    assert sorted(r[0] for r in rows) == sorted({t for t, _ in TOPICS.values()})
    for topic_type, encoding, text, digest in rows:
        assert (encoding, text) == message_definition(topic_type) and digest == type_hash(topic_type)
    topic_rows = db.execute("SELECT name, offered_qos_profiles FROM topics ORDER BY id").fetchall()
    assert [r[0] for r in topic_rows] == [*TOPICS, "/never"]
    assert yaml.safe_load(topic_rows[0][1]) == [qos_profile_dict(SENSOR_QOS)]
    assert yaml.safe_load(db.execute("SELECT metadata FROM metadata").fetchone()[0])["message_count"] == 2100
    db.close()


@pytest.mark.parametrize("preset", ["", "none", "fastwrite", "zstd_fast", "zstd_small"])
def test_every_mcap_preset_is_readable(tmp_path: Path, preset: str) -> None:
    bag = tmp_path / "bag"
    with BagWriter(bag, storage_preset_profile=preset) as writer:
        for name in TOPICS:
            writer.add_topic(topic_info(name))
        written = write_messages(writer, mixed_plan(9))
    check_metadata_matches(bag, written)
    expected = sorted((w.topic, w.log_time, w.fields) for w in written)
    assert sorted(read_rosbags(bag)) == expected
    assert sorted((t, log, f) for t, log, _, _, f in read_mcap(bag / "bag_0.mcap")) == expected
    with open(bag / "bag_0.mcap", "rb") as file:
        summary = make_reader(file).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == 9
    compressions = {c.compression for c in summary.chunk_indexes}
    if preset == "fastwrite":
        assert summary.chunk_indexes == []
    else:
        assert compressions == ({"zstd"} if preset.startswith("zstd") else {""})


@pytest.mark.parametrize("preset", ["", "resilient"])
def test_sqlite_presets_leave_no_journal(tmp_path: Path, preset: str) -> None:
    bag = tmp_path / "bag"
    with BagWriter(bag, storage_id="sqlite3", storage_preset_profile=preset) as writer:
        writer.add_topic(topic_info("/imu"))
        written = write_messages(writer, [("/imu", i) for i in range(50)])
    assert sorted(os.listdir(bag)) == ["bag_0.db3", "metadata.yaml"]
    assert len(read_rosbags(bag)) == len(written) == 50


def test_sqlite_definition_rows_carry_the_hash_of_their_text(tmp_path: Path) -> None:
    """A publisher announcing another version of a type does not make the stored text lie."""
    foreign = "RIHS01_" + "ab" * 32
    with BagWriter(tmp_path / "bag", storage_id="sqlite3") as writer:
        writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String", type_description_hash=foreign))
    db = sqlite3.connect(tmp_path / "bag" / "bag_0.db3")
    assert db.execute("SELECT type_description_hash FROM topics").fetchall() == [(foreign,)]
    assert db.execute("SELECT type_description_hash FROM message_definitions").fetchall() == \
        [(type_hash("std_msgs/msg/String"),)]
    db.close()


def test_message_larger_than_chunk_is_indexed(tmp_path: Path) -> None:
    bag = tmp_path / "big"
    image = serialize_message(make_image(1))
    assert len(image) > DEFAULT_CHUNK_SIZE
    with BagWriter(bag) as writer:
        writer.add_topic(topic_info("/camera/image_raw"))
        writer.add_topic(topic_info("/chatter"))
        written = write_messages(writer, [("/chatter", 0), ("/camera/image_raw", 1), ("/chatter", 2)])
    with open(bag / "big_0.mcap", "rb") as file:
        summary = make_reader(file).get_summary()
    assert summary is not None
    image_channel = next(c.id for c in summary.channels.values() if c.topic == "/camera/image_raw")
    big_chunks = [c for c in summary.chunk_indexes if image_channel in c.message_index_offsets]
    assert len(big_chunks) == 1 and big_chunks[0].uncompressed_size > DEFAULT_CHUNK_SIZE
    assert sorted(read_rosbags(bag)) == sorted((w.topic, w.log_time, w.fields) for w in written)


def test_writes_bytearray_and_memoryview(tmp_path: Path) -> None:
    for storage_id in ("mcap", "sqlite3"):
        bag = tmp_path / storage_id
        with BagWriter(bag, storage_id=storage_id) as writer:
            writer.add_topic(topic_info("/points"))
            written = write_messages(writer, [("/points", 0)], wrap=bytearray)
            written += write_messages(writer, [("/points", 1)], start=T0 + 1, wrap=memoryview)
        assert sorted(read_rosbags(bag)) == sorted((w.topic, w.log_time, w.fields) for w in written)


def mcap_layout(path: Path) -> tuple[int, int]:
    """Check every chunk against its message indexes and the summary's chunk index, record by record.

    Returns the number of chunks and of messages found in them.
    """
    raw = path.read_bytes()
    with open(path, "rb") as file:
        summary = make_reader(file).get_summary()
    assert summary is not None and summary.statistics is not None
    chunk_indexes = {index.chunk_start_offset: index for index in summary.chunk_indexes}
    position, chunks, messages = 8, 0, 0
    while True:
        opcode, length = struct.unpack_from("<BQ", raw, position)
        if opcode == 0x0F:  # data end
            break
        end = position + 9 + length
        if opcode != 0x06:  # not a chunk
            position = end
            continue
        start_ns, end_ns, size, _crc, name_length = struct.unpack_from("<QQQII", raw, position + 9)
        compression = raw[position + 41:position + 41 + name_length].decode()
        (compressed_size,) = struct.unpack_from("<Q", raw, position + 41 + name_length)
        body = raw[position + 49 + name_length:end]
        assert len(body) == compressed_size
        records = body if not compression else zstandard.ZstdDecompressor().decompress(body, max_output_size=size)
        assert len(records) == size
        found = {}  # offset in the chunk -> (channel, log time)
        offset = 0
        while offset < size:
            record_opcode, record_length = struct.unpack_from("<BQ", records, offset)
            assert record_opcode in (0x03, 0x04, 0x05)  # schema, channel, message
            if record_opcode == 0x05:
                channel_id, _sequence, log_time = struct.unpack_from("<HIQ", records, offset + 9)
                found[offset] = (channel_id, log_time)
            offset += 9 + record_length
        assert offset == size and found
        assert (start_ns, end_ns) == (min(t for _, t in found.values()), max(t for _, t in found.values()))
        index = chunk_indexes.pop(position)
        assert (index.chunk_length, index.uncompressed_size, index.compressed_size, index.compression) == \
            (end - position, size, compressed_size, compression)
        # The message indexes follow the chunk and list every message in it exactly once.
        indexed = {}
        index_position = end
        while raw[index_position] == 0x07:
            (index_length,) = struct.unpack_from("<Q", raw, index_position + 1)
            channel_id, entries_length = struct.unpack_from("<HI", raw, index_position + 9)
            assert index.message_index_offsets[channel_id] == index_position
            for n in range(entries_length // 16):
                log_time, message_offset = struct.unpack_from("<QQ", raw, index_position + 15 + 16 * n)
                indexed[message_offset] = (channel_id, log_time)
            index_position += 9 + index_length
        assert indexed == found
        assert index.message_index_length == index_position - end
        assert len(index.message_index_offsets) == len({channel for channel, _ in found.values()})
        chunks += 1
        messages += len(found)
        position = index_position
    assert not chunk_indexes  # every chunk index names a chunk
    return chunks, messages


@pytest.mark.parametrize("preset", ["", "zstd_fast", "zstd_small", "fastwrite"])
def test_chunks_indexes_and_buffers(tmp_path: Path, preset: str) -> None:
    """Messages of every size and buffer kind, including ones that fill a chunk alone or with others
    (written in place, from the caller's buffers); the caller may reuse its buffers after write()."""
    bag = tmp_path / "bag"
    sizes = [10, 5_000, DEFAULT_CHUNK_SIZE - 100, 300_000, 3 * DEFAULT_CHUNK_SIZE, 64 * 1024, 1, 700_000,
             DEFAULT_CHUNK_SIZE + 1, 0, 2_000_000, 17]
    expected = []
    with BagWriter(bag, storage_preset_profile=preset) as writer:
        writer.add_topic(topic_info("/chatter"))
        writer.add_topic(topic_info("/points"))
        for n, size in enumerate(sizes):
            payload = bytearray(np.random.default_rng(n).integers(0, 256, size, dtype=np.uint8).tobytes())
            topic = "/points" if n % 2 else "/chatter"
            expected.append((topic, T0 + n, bytes(payload)))
            if n % 3 == 0:
                data: Any = payload
            elif n % 3 == 1:
                data = memoryview(payload)
            else:
                data = SerializedBuffers((bytes(payload[:7]), memoryview(payload)[7:size - 3],
                                          memoryview(payload)[size - 3:] if size >= 10 else b""))
            writer.write(topic, data, T0 + n, T0 + n)
            payload[:] = bytes(size)  # reused by the caller: what was written must not change
    path = bag / "bag_0.mcap"
    with open(path, "rb") as file:
        read = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(file).iter_messages()]
    assert read == expected
    with Reader(bag) as reader:
        assert [(c.topic, t, bytes(r)) for c, t, r in reader.messages()] == expected
    if preset == "fastwrite":
        return
    chunks, messages = mcap_layout(path)
    assert messages == len(sizes) and (2 if preset == "zstd_small" else 5) <= chunks < len(sizes)


@pytest.mark.parametrize("gather", [0, GATHER])
@pytest.mark.parametrize("preset", ["", "fastwrite", "zstd_fast"])
def test_big_payloads_go_to_the_disk_in_place_behind_padding_records(
    tmp_path: Path, preset: str, gather: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Images (as the recorder hands them over: views of the message's pixels, or rclpy's bytes) are written
    from their own memory behind padding records, and every reader, indexed or linear, skips the padding;
    whether the writes are gathered (as the recorder's) or not."""
    files: list[Any] = []
    real_open = mcap_storage.open_exclusive

    def remember(path: Path, buffering: int, gather_bytes: int) -> Any:
        files.append(real_open(path, buffering, gather_bytes))
        return files[-1]

    monkeypatch.setattr(mcap_storage, "open_exclusive", remember)
    bag = tmp_path / "bag"
    topics = ("/camera/image_raw", "/imu", "/chatter")
    written = []
    with BagWriter(bag, storage_preset_profile=preset, gather_bytes=gather) as writer:
        for topic in topics:
            writer.add_topic(topic_info(topic))
        for n in range(24):
            topic = topics[n % 3]
            type_name, make = TOPICS[topic]
            msg = make(n)
            writer.write(topic, cdr_fast.serialize(msg) if n % 2 else serialize_message(msg), T0 + n, T0 + n)
            written.append((topic, T0 + n, message_fields(type_name, msg)))
    [file] = files
    assert isinstance(file, DirectFile)  # the test filesystem supports O_DIRECT; else this tests nothing
    path = bag / "bag_0.mcap"
    raw = path.read_bytes()
    padding, position = [], 8
    while raw[position] != 0x0F:  # every record up to the data end
        opcode, length = struct.unpack_from("<BQ", raw, position)
        if opcode == PADDING_OPCODE:
            padding.append(raw[position + 9:position + 9 + length])
        position += 9 + length
    frames = 8 * len(serialize_message(make_image(0)))
    if preset == "zstd_fast":  # compressed chunks are new bytes, not the caller's memory: nothing to align
        assert not padding
    else:
        assert 0 < len(padding) <= 8 and all(not any(body) for body in padding)
        assert file.in_place > 0.98 * frames
    assert sorted(read_rosbags(bag)) == sorted(written)
    assert sorted((t, log, f) for t, log, _, _, f in read_mcap(path)) == sorted(written)
    with open(path, "rb") as stream:  # linear, record by record, as a reader without the summary goes
        linear = [record.log_time for record in StreamReader(stream).records if isinstance(record, Message)]
    assert linear == [log for _, log, _ in written]
    with BagReader(bag) as reader:
        assert [m.log_time_ns for m in reader.messages()] == [log for _, log, _ in written]
    with open(path, "rb") as stream:
        found = scan(stream, len(raw), check_chunks=True)  # what bag recover sees: all of it intact
    assert found.damage is None and sum(sum(unit.counts.values()) for unit in found.units) == len(written)
    if preset == "":
        assert mcap_layout(path)[1] == len(written)


# --- splitting --------------------------------------------------------------------------------


def check_split_bag(bag: Path, written: list[Written], storage_id: str) -> dict:
    meta = check_metadata_matches(bag, written)
    assert sorted(read_rosbags(bag)) == sorted((w.topic, w.log_time, w.fields) for w in written)
    for entry in meta["files"]:
        path = bag / entry["path"]
        if storage_id == "mcap":
            times = [log for _, log, _, _, _ in read_mcap(path)]
        else:
            with Reader(path) as reader:
                times = [timestamp for _, timestamp, _ in reader.messages()]
        assert entry["message_count"] == len(times) > 0
        assert entry["starting_time"]["nanoseconds_since_epoch"] == min(times)
        assert entry["duration"]["nanoseconds"] == max(times) - min(times)
    return meta


@pytest.mark.parametrize("storage_id", ["mcap", "sqlite3"])
def test_split_by_size(tmp_path: Path, storage_id: str) -> None:
    bag = tmp_path / "sized"
    events: list[tuple[str, str]] = []
    with BagWriter(bag, storage_id=storage_id, max_bagfile_size=200_000,
                   on_split=lambda a, b: events.append((a, b))) as writer:
        for name in ("/points", "/imu", "/chatter"):
            writer.add_topic(topic_info(name))
        plan = [(name, i) for i in range(30) for name in ("/points", "/imu", "/chatter")]
        written = write_messages(writer, plan)
        assert writer.bytes_written > 30 * 12_000
    meta = check_split_bag(bag, written, storage_id)
    files = meta["relative_file_paths"]
    ext = ".mcap" if storage_id == "mcap" else ".db3"
    assert len(files) >= 2 and files == [f"sized_{n}{ext}" for n in range(len(files))]
    paths = [str(bag / f) for f in files]
    assert events == list(zip(paths, [*paths[1:], ""], strict=True))
    for path in paths[:-1]:  # every closed file got to the limit
        assert os.path.getsize(path) >= 200_000


def test_split_by_duration(tmp_path: Path) -> None:
    bag = tmp_path / "timed"
    with BagWriter(bag, max_bagfile_duration=0.25) as writer:
        writer.add_topic(topic_info("/imu"))
        writer.add_topic(topic_info("/chatter"))
        written = write_messages(writer, [("/imu", i) for i in range(20)], step=100_000_000)
    meta = check_split_bag(bag, written, "mcap")
    # 0.1 s apart, a file may span at most 0.25 s: three messages (0.2 s) per file.
    assert [f["message_count"] for f in meta["files"]] == [3, 3, 3, 3, 3, 3, 2]
    assert all(f["duration"]["nanoseconds"] == 200_000_000 for f in meta["files"][:-1])
    assert {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]} == \
        {"/imu": 20, "/chatter": 0}


@pytest.mark.parametrize("storage_id", ["mcap", "sqlite3"])
def test_circular_split_by_duration_keeps_the_newest_files(tmp_path: Path, storage_id: str) -> None:
    """max_bag_files with max_bagfile_duration (the recorder's circular test splits by size): as in
    test_split_by_duration, 0.1 s apart and at most 0.25 s per file is three messages per file, seven files
    for twenty; the newest two stay, with the last five messages."""
    bag = tmp_path / "ring"
    ext = ".mcap" if storage_id == "mcap" else ".db3"
    with BagWriter(bag, storage_id=storage_id, max_bagfile_duration=0.25, max_bag_files=2) as writer:
        writer.add_topic(topic_info("/imu"))
        written = write_messages(writer, [("/imu", i) for i in range(20)], step=100_000_000)
    assert writer.deleted_files == [f"ring_{n}{ext}" for n in range(5)]
    # the bag holds the last five; the writer wrote twenty, the deleted files' fifteen included
    assert (writer.topic_message_counts, writer.written_message_counts) == ({"/imu": 5}, {"/imu": 20})
    assert sorted(p.name for p in bag.iterdir() if p.suffix == ext) == [f"ring_5{ext}", f"ring_6{ext}"]
    meta = check_split_bag(bag, written[-5:], storage_id)
    assert meta["relative_file_paths"] == [f"ring_5{ext}", f"ring_6{ext}"]
    assert [f["message_count"] for f in meta["files"]] == [3, 2]


@pytest.mark.parametrize("storage_id", ["mcap", "sqlite3"])
def test_manual_split(tmp_path: Path, storage_id: str) -> None:
    bag = tmp_path / "manual"
    events: list[tuple[str, str]] = []
    writer = BagWriter(bag, storage_id=storage_id, on_split=lambda a, b: events.append((a, b)))
    writer.add_topic(topic_info("/chatter"))
    written = write_messages(writer, [("/chatter", i) for i in range(3)])
    writer.split()
    # Between splits metadata.yaml already lists the closed file, so a crash leaves a readable bag.
    assert load_metadata(bag)["relative_file_paths"] == [f"manual_0{Path(events[0][0]).suffix}"]
    assert len(read_rosbags(bag)) == 3
    writer.add_topic(topic_info("/imu"))  # a topic added after a split is in the new file
    written += write_messages(writer, [("/imu", i) for i in range(4)], start=T0 + 10**9)
    writer.close()
    writer.close()  # idempotent
    assert len(events) == 2 and events[0][1] == events[1][0] and events[1][1] == ""
    meta = check_split_bag(bag, written, storage_id)
    assert [f["message_count"] for f in meta["files"]] == [3, 4]
    with pytest.raises(ValueError, match="closed"):
        writer.write("/imu", b"", T0, T0)


def test_a_split_does_not_wait_for_the_full_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The write that splits returns while the full file is still being finished (summary, fsync); the file
    is listed, and the split reported, once that is done. Before, every message waited for it."""
    release = threading.Event()
    closing = threading.Event()
    close = McapStorage.close

    def slow_close(storage: McapStorage, serialized_metadata: str = "") -> Any:
        if storage.path.name == "slow_0.mcap":
            closing.set()
            release.wait(30)  # a disk slow to take the summary and the fsync
        return close(storage, serialized_metadata)

    monkeypatch.setattr(McapStorage, "close", slow_close)
    bag = tmp_path / "slow"
    events: list[tuple[str, str]] = []
    writer = BagWriter(bag, max_bagfile_size=200_000, on_split=lambda a, b: events.append((a, b)))
    writer.add_topic(topic_info("/points"))
    written: list[Written] = []

    def write_through_the_split() -> None:
        while writer.current_file != bag / "slow_1.mcap":
            written.extend(write_messages(writer, [("/points", len(written))], start=T0 + len(written) * 10**7))
        written.extend(write_messages(writer, [("/points", len(written))], start=T0 + len(written) * 10**7))

    worker = threading.Thread(target=write_through_the_split)
    worker.start()
    worker.join(10)
    try:
        assert not worker.is_alive(), "writes waited for the full file to be finished"
        # The writes may return before the finishing thread has even begun (a busy machine): wait for it to be in
        # the slow close, which is the moment checked.
        assert closing.wait(10), "the full file was never finished"
        assert not events and writer.files == [bag / "slow_0.mcap", bag / "slow_1.mcap"]
        assert writer.topic_message_counts["/points"] == len(written)  # the closing file's messages count
    finally:
        release.set()
    deadline = time.monotonic() + 10
    while not events and time.monotonic() < deadline:
        time.sleep(0.01)
    assert events == [(str(bag / "slow_0.mcap"), str(bag / "slow_1.mcap"))]
    assert load_metadata(bag)["relative_file_paths"] == ["slow_0.mcap"]
    writer.close()
    meta = check_split_bag(bag, written, "mcap")
    assert meta["relative_file_paths"] == ["slow_0.mcap", "slow_1.mcap"]


def test_a_bug_while_finishing_a_split_off_file_stops_the_bag(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """What finishing a file in the background raises beyond I/O errors (a bug) stops the bag with an error
    at the next call; the writer never waits forever for a thread that died."""
    close = McapStorage.close

    def broken_close(storage: McapStorage, serialized_metadata: str = "") -> Any:
        if storage.path.name == "broken_0.mcap":
            raise RuntimeError("a bug")
        return close(storage, serialized_metadata)

    monkeypatch.setattr(McapStorage, "close", broken_close)
    bag = tmp_path / "broken"
    writer = BagWriter(bag, max_bagfile_size=200_000)
    writer.add_topic(topic_info("/points"))
    written: list[Written] = []
    raised: list[BaseException] = []

    def write_until_stopped() -> None:
        try:
            for index in range(1000):
                written.extend(write_messages(writer, [("/points", index)], start=T0 + index * 10**7))
        except BagWriteError as error:
            raised.append(error)

    worker = threading.Thread(target=write_until_stopped, daemon=True)
    worker.start()
    worker.join(20)
    assert not worker.is_alive(), "the writer waits for a thread that died"
    assert raised and "finishing the file failed: RuntimeError" in str(raised[0])
    writer.close()
    assert load_metadata(bag)["relative_file_paths"] == ["broken_1.mcap"]  # the unfinished file is left out
    assert 0 < len(read_rosbags(bag)) < len(written)


def test_sync_does_not_wait_for_the_disk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """sync() hands the fsync to a thread of its own (a busy disk took up to 130 ms), and a failed fsync
    stops the bag at the next call like a failed write, with everything written before it readable."""
    release = threading.Event()
    fsync = os.fsync
    calls: list[int] = []
    finished: list[int] = []

    def slow_fsync(fd: int) -> None:
        if os.path.isdir(f"/proc/self/fd/{fd}"):
            return fsync(fd)  # the bag directory's, just before the file's (docs/design/power-cut.md)
        calls.append(fd)
        try:
            if len(calls) == 1:
                release.wait(30)
                return fsync(fd)
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        finally:
            finished.append(fd)

    def wait_finished(count: int) -> None:
        """Until ``count`` fsyncs returned and the sync thread has done its bookkeeping after the call."""
        deadline = time.monotonic() + 10
        while len(finished) < count and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(finished) >= count
        for thread in threading.enumerate():
            if thread.name.startswith("bag_sync:"):
                thread.join(10)
                assert not thread.is_alive(), "the sync thread did not end"

    bag = tmp_path / "synced"
    writer = BagWriter(bag)
    writer.add_topic(topic_info("/chatter"))
    written = write_messages(writer, [("/chatter", i) for i in range(3)])
    monkeypatch.setattr(os, "fsync", slow_fsync)
    worker = threading.Thread(target=writer.sync)
    worker.start()
    worker.join(10)
    try:
        assert not worker.is_alive(), "sync() waited for the fsync"
        deadline = time.monotonic() + 10
        while not calls and time.monotonic() < deadline:  # the thread fsyncs the directory first
            time.sleep(0.01)
        assert len(calls) == 1
        written += write_messages(writer, [("/chatter", i) for i in range(3, 5)], start=T0 + 10**9)
        writer.sync()  # the first fsync still runs: no second one
        assert len(calls) == 1
    finally:
        release.set()
    wait_finished(1)
    writer.sync()  # this fsync fails with EIO ...
    wait_finished(2)
    monkeypatch.setattr(os, "fsync", fsync)
    with pytest.raises(BagWriteError, match="Input/output error"):  # ... and the next call says so
        write_messages(writer, [("/chatter", 5)], start=T0 + 2 * 10**9)
    writer.close()
    assert len(read_rosbags(bag)) == len(written) == 5


# --- errors -----------------------------------------------------------------------------------


def test_existing_uri_is_never_overwritten(tmp_path: Path) -> None:
    bag = tmp_path / "existing"
    bag.mkdir()
    (bag / "keep.txt").write_text("mine")
    with pytest.raises(BagExistsError, match="already exists") as info:
        BagWriter(bag)
    assert isinstance(info.value, FileExistsError) and info.value.filename == str(bag)
    assert os.listdir(bag) == ["keep.txt"]
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(FileExistsError):
        BagWriter(tmp_path / "a_file", storage_id="sqlite3")


def test_unwritable_location(tmp_path: Path) -> None:
    (tmp_path / "afile").write_text("not a directory")
    with pytest.raises(BagWriteError, match="cannot create bag directory") as info:
        BagWriter(tmp_path / "afile" / "bag")
    assert info.value.errno == errno.ENOTDIR and info.value.filename == str(tmp_path / "afile" / "bag")
    with pytest.raises(BagWriteError):
        BagWriter("/proc/no_bags_here")


def test_invalid_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unsupported storage_id 'rosbag1'"):
        BagWriter(tmp_path / "a", storage_id="rosbag1")
    with pytest.raises(ValueError, match="storage_preset_profile 'resilient'"):
        BagWriter(tmp_path / "b", storage_preset_profile="resilient")
    with pytest.raises(ValueError):
        BagWriter(tmp_path / "c", max_bagfile_size=-1)
    assert not any(tmp_path.iterdir())  # nothing created for invalid arguments
    with BagWriter(tmp_path / "d") as writer:
        with pytest.raises(KeyError, match="add_topic"):
            writer.write("/nope", b"", T0, T0)
        with pytest.raises(MessageDefinitionNotFoundError):
            writer.add_topic(TopicInfo("/x", "no_such_pkg/msg/Thing"))
        writer.add_topic(topic_info("/chatter"))
        with pytest.raises(ValueError, match="already recorded"):
            writer.add_topic(TopicInfo("/chatter", "sensor_msgs/msg/Imu"))
    assert load_metadata(tmp_path / "d")["message_count"] == 0


def test_default_uri_is_timestamped_in_cwd(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    with BagWriter(storage_id="") as writer:
        pass
    assert writer.path.parent == tmp_path
    assert re.fullmatch(r"rosbag2_\d{4}_\d{2}_\d{2}-\d{2}_\d{2}_\d{2}", writer.path.name)
    assert load_metadata(writer.path)["storage_identifier"] == "mcap"


DISK_FULL_CHILD = textwrap.dedent("""
    import json, resource, signal, sys
    sys.path.insert(0, {repo!r})
    from rclpy.serialization import serialize_message
    from tests.test_bag_writer import TOPICS, T0, topic_info
    from baglib.write.writer import BagWriter, BagWriteError

    storage_id, preset, topic, limit, count, bag = {args!r}
    make = TOPICS[topic][1]
    payloads = [serialize_message(make(i)) for i in range(4)]
    writer = BagWriter(bag, storage_id=storage_id, storage_preset_profile=preset)
    writer.add_topic(topic_info(topic))
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG instead
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    result = {{"attempted": 0}}
    try:
        for n in range(count):
            result["attempted"] += 1
            writer.write(topic, payloads[n % 4], T0 + n * 1000, T0 + n * 1000)
    except BagWriteError as error:
        result["error"] = [error.errno, error.filename, str(error)]
        try:
            writer.write(topic, payloads[0], T0, T0)
        except BagWriteError as again:
            result["again"] = str(again)
    try:
        writer.close()
    except BagWriteError as error:
        result["close_error"] = [error.errno, error.filename, str(error)]
    result["counts"] = writer.topic_message_counts
    print(json.dumps(result))
""")


@pytest.mark.parametrize(("storage_id", "preset", "topic", "limit", "count"), [
    ("mcap", "", "/camera/image_raw", 5_000_000, 100),
    ("mcap", "", "/imu", 3_000_000, 100_000),
    ("mcap", "", "/imu", 2_600_000, 8_000),  # the last chunk fails when close() flushes it
    ("mcap", "fastwrite", "/camera/image_raw", 5_000_000, 100),
    ("mcap", "zstd_fast", "/points", 200_000, 100_000),
    ("sqlite3", "", "/points", 20_000_000, 10_000),
    ("sqlite3", "resilient", "/imu", 1_000_000, 100_000),
])
def test_disk_full_leaves_a_readable_bag(
    tmp_path: Path, storage_id: str, preset: str, topic: str, limit: int, count: int
) -> None:
    bag = tmp_path / "full"
    script = DISK_FULL_CHILD.format(repo=str(REPO), args=(storage_id, preset, topic, limit, count, str(bag)))
    child = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                           cwd=tmp_path)
    assert child.returncode == 0, child.stderr
    result = json.loads(child.stdout.strip().splitlines()[-1])
    # The failure surfaces once, from write() or else from close(), naming the file and the reason.
    assert ("error" in result) != ("close_error" in result), result
    error_number, filename, message = result.get("error") or result["close_error"]
    assert error_number in (errno.EFBIG, errno.EIO), result
    assert filename == str(bag / f"full_0.{'mcap' if storage_id == 'mcap' else 'db3'}")
    assert re.search(r"cannot (write|finish) bag file: (File too large|sqlite3: )", message), message
    if "error" in result:
        assert "earlier failure" in result["again"]

    meta = load_metadata(bag)
    read = read_rosbags(bag)
    # Most of what was attempted made it; exactly what the metadata and the writer claim.
    assert 0 < meta["message_count"] == len(read) == result["counts"][topic] < result["attempted"]
    assert meta["message_count"] >= result["attempted"] // 4
    assert list(result["counts"].values()) == [len(read)]
    type_name, make = TOPICS[topic]
    expected = [message_fields(type_name, make(i)) for i in range(4)]
    read.sort(key=lambda item: item[1])
    assert [ts for _, ts, _ in read] == [T0 + n * 1000 for n in range(len(read))]  # a prefix
    assert all(fields == expected[n % 4] for n, (_, _, fields) in enumerate(read))
    assert sorted(os.listdir(bag)) == sorted([*meta["relative_file_paths"], "metadata.yaml"])
    if storage_id == "mcap":
        assert len(read_mcap(bag / "full_0.mcap")) == len(read)


LIMIT_SWEEP_CHILD = textwrap.dedent("""
    import json, os, resource, signal, sys
    sys.path.insert(0, {repo!r})
    from rclpy.serialization import serialize_message
    from tests.test_bag_writer import TOPICS, T0, topic_info
    from baglib.write.writer import BagWriter, BagWriteError

    plan, limits, root = {args!r}
    payloads = [serialize_message(TOPICS[topic][1](n)) for n, topic in enumerate(plan)]
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    hard = resource.getrlimit(resource.RLIMIT_FSIZE)[1]
    results = []
    full_size = None
    for limit in limits:  # None: no limit; negative: relative to the unlimited file's size
        if limit is not None and limit < 0:
            limit += full_size
        bag = f"{{root}}/bag_{{limit}}"
        writer = BagWriter(bag)
        for topic in sorted(set(plan)):
            writer.add_topic(topic_info(topic))
        resource.setrlimit(resource.RLIMIT_FSIZE, (hard if limit is None else limit, hard))
        failed = None
        try:
            for n, topic in enumerate(plan):
                writer.write(topic, payloads[n], T0 + n, T0 + n)
        except BagWriteError as error:
            failed = "write"
        try:
            writer.close()
        except BagWriteError as error:
            failed = failed or "close"
        resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))
        if limit is None:
            full_size = os.path.getsize(f"{{bag}}/bag_None_0.mcap")
        results.append([bag, failed, writer.topic_message_counts])
    print(json.dumps(results))
""")


def test_any_file_size_limit_leaves_a_consistent_bag(tmp_path: Path) -> None:
    """Fail the MCAP file at many sizes (inside the header, metadata, chunks and indexes)."""
    plan = ["/chatter", "/camera/image_raw", "/imu", "/chatter", "/camera/image_raw", "/imu",
            "/camera/image_raw"]
    image = len(serialize_message(make_image(0)))
    # Below ~3 kB not even metadata.yaml fits; above, cut through header, metadata and chunks;
    # negative limits (relative to the complete file) cut the summary written by close().
    limits = [None, *range(3_000, 30_000, 1_500), *range(image, 3 * image, 97_003),
              -1, -500, -3_000, -6_000, -12_000]
    script = LIMIT_SWEEP_CHILD.format(repo=str(REPO), args=(plan, limits, str(tmp_path)))
    child = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert child.returncode == 0, child.stderr
    outcomes = set()
    for bag, failed, counts in json.loads(child.stdout.strip().splitlines()[-1]):
        meta = load_metadata(Path(bag))
        if not meta["relative_file_paths"]:
            # Too small even for the summary: the file is left out and the bag is empty.
            assert failed and sum(counts.values()) == 0
            outcomes.add((failed, -1))
            continue
        read = sorted(read_rosbags(Path(bag)), key=lambda item: item[1])
        from_mcap = read_mcap(Path(bag) / f"{Path(bag).name}_0.mcap")
        assert meta["message_count"] == len(read) == len(from_mcap) == sum(counts.values())
        # What survives is always a prefix of what was written, decoded intact.
        assert [(topic, ts) for topic, ts, _ in read] == [(plan[n], T0 + n) for n in range(len(read))]
        assert all(fields == message_fields(TOPICS[topic][0], TOPICS[topic][1](n))
                   for n, (topic, _, fields) in enumerate(read))
        assert failed is not None or len(read) == len(plan)
        outcomes.add((failed, len(read)))
    # The sweep reached failures in write() and in close(), with empty and partial bags.
    assert {failed for failed, _ in outcomes} == {"write", "close", None}
    assert len({count for _, count in outcomes}) >= 4


@pytest.mark.parametrize("storage_id", ["mcap", "sqlite3"])
def test_the_next_file_is_prepared_before_the_split(tmp_path: Path, storage_id: str) -> None:
    bag = tmp_path / "ahead"
    ext = ".mcap" if storage_id == "mcap" else ".db3"
    events: list[tuple[str, str]] = []
    written: list[Written] = []

    def write_until(topic: str, done: Callable[[], bool]) -> None:
        for i in range(1000):
            if done():
                return
            written.extend(write_messages(writer, [(topic, i)], start=T0 + len(written) * 10_000_000))
        raise AssertionError("never happened")

    writer = BagWriter(bag, storage_id=storage_id, max_bagfile_size=200_000,
                       on_split=lambda a, b: events.append((a, b)))
    writer.add_topic(topic_info("/points"))
    write_until("/points", (bag / f"ahead_1{ext}").exists)
    assert writer.files == [bag / f"ahead_0{ext}"] and not events  # not split yet, but the next file is ready
    writer.add_topic(topic_info("/imu"))  # a topic added now goes into the prepared file too
    write_until("/points", lambda: writer.current_file == bag / f"ahead_1{ext}")  # the prepared file
    deadline = time.monotonic() + 10
    while not events and time.monotonic() < deadline:
        time.sleep(0.01)
    assert events[0] == (str(bag / f"ahead_0{ext}"), str(bag / f"ahead_1{ext}"))  # listed in metadata.yaml now
    assert load_metadata(bag)["relative_file_paths"] == [f"ahead_0{ext}"]
    write_until("/imu", lambda: any(w.topic == "/imu" for w in written))
    write_until("/points", (bag / f"ahead_2{ext}").exists)
    writer.close()  # the prepared ahead_2 was never used: removed
    meta = check_split_bag(bag, written, storage_id)
    assert sorted(p.name for p in bag.glob(f"*{ext}")) == sorted(meta["relative_file_paths"])
    assert not (bag / f"ahead_2{ext}").exists()
