"""The bag reader against bags written by this project's writer and by ``rosbags``: everything read back is
compared with what was written and with what ``rosbags`` (an independent reader) reads from the same bag.
Older rosbag2 layouts are in test_bag_reader_formats.py.
"""
from __future__ import annotations

import logging
import os
import random
import shutil
import sqlite3
from pathlib import Path
from typing import Any

import pytest
import yaml
from rclpy.duration import Duration, Infinite
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.typesys import Stores, get_typestore
from std_msgs.msg import String

from baglib.format.message_definitions import message_definition
from baglib.format.metadata import TopicInfo, qos_profile_dict
from baglib.read.reader import BagMessage, BagReadError, BagReader
from baglib.tools.repair import recover_bag
from baglib.write.writer import BagWriter

T0 = 1_718_000_000_000_000_000
SENSOR_QOS = qos_profile_dict(QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE, deadline=Infinite, lifespan=Duration(seconds=2),
    liveliness=LivelinessPolicy.AUTOMATIC, liveliness_lease_duration=Infinite))
LATCHED_QOS = qos_profile_dict(QoSProfile(
    history=HistoryPolicy.KEEP_ALL, depth=0, reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL))
Message = tuple[str, int, bytes]


# --- helpers ------------------------------------------------------------------------------------------


def payload(i: int, size: int) -> bytes:
    """A CDR-looking message of ``size`` bytes that differs per ``i`` (incompressible, like pixels)."""
    return (b"\x00\x01\x00\x00" + i.to_bytes(4, "little") + random.Random(i).randbytes(size))[:size]


def read(bag: Path | str, **filters: Any) -> list[Message]:
    with BagReader(bag) as reader:
        return [(m.connection.topic, m.log_time_ns, bytes(m.data)) for m in reader.messages(**filters)]


def read_rosbags(bag: Path) -> list[Message]:
    with Reader(bag) as reader:
        return [(connection.topic, timestamp, bytes(data)) for connection, timestamp, data in reader.messages()]


def rosbags_qos(profile: Qos) -> dict[str, Any]:
    """A rosbags QoS profile in rosbag2's version-9 dict form (the form Connection uses)."""
    return {"history": profile.history.name.lower(), "depth": profile.depth,
            "reliability": profile.reliability.name.lower(), "durability": profile.durability.name.lower(),
            "deadline": profile.deadline._asdict(), "lifespan": profile.lifespan._asdict(),
            "liveliness": profile.liveliness.name.lower(),
            "liveliness_lease_duration": profile.liveliness_lease_duration._asdict(),
            "avoid_ros_namespace_conventions": profile.avoid_ros_namespace_conventions}


def check_connections_like_rosbags(bag: Path) -> None:
    """Topic, type, QoS, hash, count and message definition of each connection equal rosbags' view."""
    with BagReader(bag) as ours, Reader(bag) as theirs:
        assert [c.id for c in ours.connections] == list(range(len(ours.connections)))
        assert len(ours.connections) == len(theirs.connections)
        for mine, other in zip(ours.connections, theirs.connections, strict=True):
            assert (mine.topic, mine.msgtype, mine.type_description_hash, mine.message_count) == \
                   (other.topic, other.msgtype, other.digest, other.msgcount)
            assert mine.serialization_format == other.ext.serialization_format == "cdr"
            assert list(mine.offered_qos_profiles) == [rosbags_qos(q) for q in other.ext.offered_qos_profiles]
            assert mine.message_definition is not None
            assert mine.message_definition == (other.msgdef.format.name.replace("MSG", "ros2msg")
                                               .replace("IDL", "ros2idl"), other.msgdef.data)
        assert (ours.message_count, ours.starting_time_ns, ours.end_time_ns) == \
               (theirs.message_count, theirs.start_time, theirs.end_time - 1)
        assert ours.duration_ns == ours.end_time_ns - ours.starting_time_ns


def write_bag(path: Path, storage_id: str, preset: str, written: list[tuple[str, int, bytes]],
              split_bytes: int = 0, **options: Any) -> None:
    """Write ``written`` (topic, log time, data) with BagWriter; publish time is log time + 7."""
    with BagWriter(path, storage_id=storage_id, storage_preset_profile=preset, max_bagfile_size=split_bytes,
                   **options) as writer:
        writer.add_topic(TopicInfo("/camera", "sensor_msgs/msg/Image", offered_qos_profiles=[SENSOR_QOS]))
        writer.add_topic(TopicInfo("/chatter", "std_msgs/String", offered_qos_profiles=[LATCHED_QOS, SENSOR_QOS]))
        writer.add_topic(TopicInfo("/silent", "std_msgs/msg/String"))
        for topic, log_time, data in written:
            writer.write(topic, data, log_time, log_time + 7)


def sensor_stream(count: int, image_size: int = 120_000) -> list[Message]:
    """Camera frames (every 7th one bigger than an MCAP chunk) and chatter, in log-time order, with
    runs of equal log times."""
    stream = []
    for i in range(count):
        if i % 3:
            stream.append(("/chatter", T0 + i // 2 * 1000, serialize_message(String(data=f"hello {i}"))))
        else:
            size = 900_000 if i % 7 == 0 else image_size
            stream.append(("/camera", T0 + i // 2 * 1000, payload(i, size)))
    return stream


WRITER_VARIANTS = [("mcap", ""), ("mcap", "fastwrite"), ("mcap", "zstd_fast"), ("mcap", "zstd_small"),
                   ("sqlite3", "")]


@pytest.fixture(scope="module")
def writer_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, str], Path]:
    """One split bag per storage and preset, all holding :func:`sensor_stream`."""
    root = tmp_path_factory.mktemp("writer_bags")
    bags = {}
    for storage_id, preset in WRITER_VARIANTS:
        bag = root / f"{storage_id}_{preset or 'default'}"
        write_bag(bag, storage_id, preset, sensor_stream(120), split_bytes=2_500_000,
                  custom_data={"robot": "r2"})
        bags[storage_id, preset] = bag
    return bags


# --- bags this project writes -------------------------------------------------------------------------


@pytest.mark.parametrize("variant", WRITER_VARIANTS, ids=lambda v: "-".join(filter(None, v)))
def test_writer_bags_read_back_like_rosbags(variant: tuple[str, str], writer_bags: dict) -> None:
    bag = writer_bags[variant]
    written = sensor_stream(120)
    with BagReader(bag) as reader:
        assert reader.storage_id == variant[0] and len(reader.files) >= 3
        assert reader.files == sorted(bag.glob(f"*{'.mcap' if variant[0] == 'mcap' else '.db3'}"),
                                      key=lambda p: int(p.stem.rsplit("_", 1)[1]))
        assert (reader.ros_distro, reader.custom_data) == ("jazzy", {"robot": "r2"})
        assert [(c.topic, c.msgtype, c.message_count) for c in reader.connections] == [
            ("/camera", "sensor_msgs/msg/Image", 40), ("/chatter", "std_msgs/msg/String", 80),
            ("/silent", "std_msgs/msg/String", 0)]
        assert reader.connections[1].offered_qos_profiles == (LATCHED_QOS, SENSOR_QOS)
        assert reader.connections[1].message_definition == message_definition("std_msgs/msg/String")
        messages = list(reader.messages())
    assert [(m.connection.topic, m.log_time_ns, bytes(m.data)) for m in messages] == written
    publish_offset = 7 if variant[0] == "mcap" else 0  # sqlite3 stores no publish time
    assert all(m.publish_time_ns == m.log_time_ns + publish_offset for m in messages)
    assert [m.file_index for m in messages] == sorted(m.file_index for m in messages)
    assert read_rosbags(bag) == written
    check_connections_like_rosbags(bag)


def test_uncompressed_chunks_are_read_without_a_copy_per_message(writer_bags: dict) -> None:
    with BagReader(writer_bags["mcap", ""]) as reader:
        messages = list(reader.messages(["/camera"]))
    # Several frames of one chunk are views of the one buffer the chunk was read into.
    buffers = [m.data.obj for m in messages if isinstance(m.data, memoryview)]
    assert len(buffers) == len(messages)
    assert len({id(buffer) for buffer in buffers}) < len(messages) / 2


def test_each_storage_file_reads_alone(writer_bags: dict) -> None:
    for (storage_id, preset), bag in writer_bags.items():
        with BagReader(bag) as whole:
            by_file: dict[int, list[BagMessage]] = {}
            for message in whole.messages():
                by_file.setdefault(message.file_index, []).append(message)
            for index, path in enumerate(whole.files):
                with BagReader(path) as single:
                    assert single.storage_id == storage_id and single.files == [path]
                    assert single.ros_distro == "jazzy"
                    mine = [(m.connection.topic, m.log_time_ns, bytes(m.data)) for m in single.messages()]
                    assert mine == [(m.connection.topic, m.log_time_ns, bytes(m.data)) for m in by_file[index]]
                    counts = {c.topic: c.message_count for c in single.connections}
                    assert sum(counts.values()) == single.message_count == len(mine)
                    assert counts["/camera"] == sum(1 for topic, _, _ in mine if topic == "/camera")
                    assert (single.starting_time_ns, single.end_time_ns) == (mine[0][1], mine[-1][1])


@pytest.mark.parametrize("variant", WRITER_VARIANTS, ids=lambda v: "-".join(filter(None, v)))
def test_filters(variant: tuple[str, str], writer_bags: dict) -> None:
    bag = writer_bags[variant]
    everything = read(bag)
    times = sorted({log_time for _, log_time, _ in everything})
    for topics, start, stop in [(None, times[10], None), (None, None, times[50]), (["/camera"], times[5], times[40]),
                                (["/chatter", "/silent"], None, None), ("/chatter", times[-1], None),
                                (["/nothing"], None, None), (None, times[-1] + 1, None), (None, None, times[0]),
                                ([], None, None)]:
        expected = [m for m in everything if (topics is None or m[0] in ([topics] if isinstance(topics, str)
                                                                         else topics))
                    and (start is None or m[1] >= start) and (stop is None or m[1] < stop)]
        assert read(bag, topics=topics, start_ns=start, stop_ns=stop) == expected, (topics, start, stop)


def test_messages_can_be_read_again_and_interleaved(writer_bags: dict) -> None:
    """A player seeks by calling messages() again; passes are independent of each other."""
    with BagReader(writer_bags["mcap", ""]) as reader:
        everything = list(reader.messages())
        first = reader.messages()
        head = [next(first) for _ in range(10)]
        middle = everything[60].log_time_ns
        second = list(reader.messages(start_ns=middle))
        rest = list(first)
    assert head + rest == everything
    assert second == [m for m in everything if m.log_time_ns >= middle]


@pytest.mark.parametrize("variant", [("mcap", ""), ("mcap", "fastwrite"), ("mcap", "zstd_small"), ("sqlite3", "")],
                         ids=lambda v: "-".join(filter(None, v)))
def test_out_of_order_writes_come_out_in_time_order_keeping_bag_order_for_ties(variant: tuple[str, str],
                                                                             tmp_path: Path) -> None:
    """Log times written out of order: chunks overlap, chunks hold messages out of order and the split
    files overlap in time. Messages come out by log time; equal log times in the order they were
    written (which is file order, then order in the file)."""
    rng = random.Random(4)
    written = [("/camera" if i % 2 else "/chatter", T0 + rng.randrange(40) * 1000, payload(i, 150_000))
               for i in range(160)]
    bag = tmp_path / "shuffled"
    write_bag(bag, *variant, written, split_bytes=6_000_000)
    with BagReader(bag) as reader:
        assert len(reader.files) >= 3
        messages = list(reader.messages())
    assert [(m.connection.topic, m.log_time_ns, bytes(m.data)) for m in messages] == \
           sorted(written, key=lambda message: message[1])
    start, stop = T0 + 10_000, T0 + 30_000
    assert read(bag, topics=["/camera"], start_ns=start, stop_ns=stop) == [
        m for m in sorted(written, key=lambda message: message[1]) if m[0] == "/camera" and start <= m[1] < stop]


@pytest.mark.parametrize("variant", [("mcap", ""), ("mcap", "fastwrite"), ("sqlite3", "")],
                         ids=lambda v: "-".join(filter(None, v)))
def test_equal_log_times_across_a_split_keep_write_order(variant: tuple[str, str], tmp_path: Path) -> None:
    written = [("/chatter" if i % 3 else "/camera", T0 + (i >= 40) * 1000, payload(i, 60_000)) for i in range(80)]
    bag = tmp_path / "ties"
    write_bag(bag, *variant, written, split_bytes=1_500_000)
    with BagReader(bag) as reader:
        messages = list(reader.messages())
        assert len({m.file_index for m in messages if m.log_time_ns == T0}) >= 2
    assert [(m.connection.topic, m.log_time_ns, bytes(m.data)) for m in messages] == written


# --- bags rosbags writes ------------------------------------------------------------------------------

ROSBAGS_VARIANTS = [(storage, mode, version)
                    for storage in (StoragePlugin.MCAP, StoragePlugin.SQLITE3)
                    for mode in (CompressionMode.NONE, CompressionMode.FILE, CompressionMode.MESSAGE,
                                 CompressionMode.STORAGE)
                    for version in (8, 9)
                    if not (storage == StoragePlugin.SQLITE3 and mode == CompressionMode.STORAGE)]


@pytest.mark.parametrize("variant", ROSBAGS_VARIANTS, ids=lambda v: f"{v[0].name}-{v[1].name}-v{v[2]}")
def test_rosbags_bags_read_back_like_rosbags(variant: tuple[StoragePlugin, CompressionMode, int],
                                             tmp_path: Path) -> None:
    storage, mode, version = variant
    typestore = get_typestore(Stores.ROS2_JAZZY)
    qos = Qos(QosHistory.KEEP_LAST, 10, QosReliability.BEST_EFFORT, QosDurability.TRANSIENT_LOCAL,
              QosTime(0, 0), QosTime(3, 500), QosLiveliness.AUTOMATIC, QosTime(9223372036, 854775807), False)
    bag = tmp_path / "rosbags_bag"
    written = []
    writer = Writer(bag, version=version, storage_plugin=storage)
    if mode != CompressionMode.NONE:
        writer.set_compression(mode, CompressionFormat.ZSTD)
    writer.set_custom_data("site", "lab")
    with writer:
        strings = writer.add_connection("/strings", "std_msgs/msg/String", typestore=typestore,
                                        offered_qos_profiles=[qos])
        images = writer.add_connection("/image", "sensor_msgs/msg/Image", typestore=typestore)
        for i in range(60):
            connection, data = (images, payload(i, 50_000)) if i % 4 == 0 else \
                (strings, serialize_message(String(data=f"s{i}")))
            timestamp = T0 + (i // 3) * 10  # equal timestamps in threes
            writer.write(connection, timestamp, data)
            written.append((connection.topic, timestamp, data))
    assert read(bag) == read_rosbags(bag) == written
    check_connections_like_rosbags(bag)
    with BagReader(bag) as reader:
        assert reader.custom_data == {"site": "lab"} and reader.ros_distro == "rosbags"
        assert reader.connections[0].offered_qos_profiles == (rosbags_qos(qos),)
        assert read(bag, topics=["/image"], start_ns=T0 + 50) == [m for m in written
                                                                   if m[0] == "/image" and m[1] >= T0 + 50]


# --- a bag a crash left behind ------------------------------------------------------------------------


@pytest.mark.parametrize("preset", ["", "fastwrite", "zstd_fast"])
def test_truncated_mcap_reads_what_is_complete(preset: str, tmp_path: Path,
                                               caplog: pytest.LogCaptureFixture) -> None:
    """An MCAP file cut anywhere (no summary) reads linearly up to its first incomplete record: the
    same messages ``bag recover`` keeps (checked with rosbags reading the recovered copy)."""
    written = sensor_stream(90, image_size=200_000)
    bag = tmp_path / "full"
    write_bag(bag, "mcap", preset, written)
    (path,) = bag.glob("*.mcap")
    size = path.stat().st_size
    previous = -1
    for fraction in (0.02, 0.3, 0.55, 0.8, 0.97):
        cut = tmp_path / f"cut_{fraction}"
        shutil.copytree(bag, cut)
        os.truncate(cut / path.name, int(size * fraction))
        with caplog.at_level(logging.WARNING, logger="baglib.read.mcap_reader"):
            caplog.clear()
            messages = read(cut)
        assert "has no summary" in caplog.text
        assert messages == written[:len(messages)]
        assert previous <= len(messages) < len(written)
        previous = len(messages)
        assert read(cut / path.name) == messages  # the file alone, without metadata.yaml
        recovered = tmp_path / f"recovered_{fraction}"
        assert recover_bag(cut, recovered).readable
        assert read_rosbags(recovered) == messages
    assert previous > len(written) // 2


def test_missing_metadata_names_bag_recover(writer_bags: dict, tmp_path: Path) -> None:
    bag = tmp_path / "unfinished"
    shutil.copytree(writer_bags["mcap", ""], bag)
    (bag / "metadata.yaml").unlink()
    with pytest.raises(BagReadError, match=f"'{bag}' is an unfinished bag.*ipc-component bag recover {bag}"):
        BagReader(bag)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(BagReadError, match="is not a bag: no metadata.yaml"):
        BagReader(empty)
    with pytest.raises(BagReadError, match="does not exist"):
        BagReader(tmp_path / "nowhere")


def edit_metadata(source: Path, target: Path, **changes: Any) -> Path:
    shutil.copytree(source, target)
    document = yaml.safe_load((target / "metadata.yaml").read_text())
    document["rosbag2_bagfile_information"].update(changes)
    (target / "metadata.yaml").write_text(yaml.safe_dump(document))
    return target


def test_unsupported_bags_are_named_clearly(writer_bags: dict, tmp_path: Path) -> None:
    source = writer_bags["mcap", ""]
    cases = [
        ({"version": 10}, r"metadata.yaml: metadata version 10 is not supported \(this reader reads versions 4 to 9\)"),
        ({"version": 3}, "metadata version 3 is not supported"),
        ({"storage_identifier": "rosbag_v2"}, r"metadata.yaml: unknown storage id 'rosbag_v2' \(this reader reads "
                                              r"mcap, sqlite3\)"),
        ({"compression_mode": "FILE", "compression_format": "lz4"}, "compression format 'lz4' is not supported"),
        ({"compression_mode": "CHUNK", "compression_format": "zstd"}, "unknown compression mode 'chunk'"),
        ({"relative_file_paths": ["lost_0.mcap"]}, "metadata.yaml lists lost_0.mcap, which is not in"),
        ({"topics_with_message_count": [{"topic_metadata": {"name": "/x", "type": "a/msg/B",
                                                            "serialization_format": "cdr",
                                                            "offered_qos_profiles": [{"depth": 1}]},
                                         "message_count": 0}]}, "topic '/x': a QoS profile lacks history"),
        ({"duration": None}, r"metadata.yaml: malformed entry"),
    ]
    for number, (changes, message) in enumerate(cases):
        bag = edit_metadata(source, tmp_path / f"case{number}", **changes)
        with pytest.raises(BagReadError, match=message):
            BagReader(bag)
    with pytest.raises(BagReadError, match="unknown storage id 'bag' for"):
        BagReader(source, storage_id="bag")
    (tmp_path / "notes.txt").write_text("not a bag")
    with pytest.raises(BagReadError, match="neither an MCAP nor an SQLite3 file"):
        BagReader(tmp_path / "notes.txt")
    with pytest.raises(BagReadError, match="is not an SQLite3 database"):
        BagReader(source, storage_id="sqlite3")


def test_closed_reader_refuses_to_read(writer_bags: dict) -> None:
    reader = BagReader(writer_bags["sqlite3", ""])
    reader.close()
    reader.close()
    with pytest.raises(BagReadError, match="closed"):
        next(reader.messages())


def test_sqlite_rows_in_a_write_ahead_log_are_read_once_recovered(tmp_path: Path) -> None:
    """A database copied while a writer in WAL mode held it (a crash): its committed rows are partly only in
    the ``-wal`` file. Replaying the log would write a ``-shm`` file next to it, and ``rosbags`` (which opens it
    immutable) misses them: the reader refuses it with the ``bag recover`` hint, and recovered it reads them."""
    bag = tmp_path / "bag"
    write_bag(bag, "sqlite3", "", [("/chatter", T0 + i, payload(i, 100)) for i in range(10)])
    (path,) = bag.glob("*.db3")
    db = sqlite3.connect(path)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA wal_autocheckpoint=0")
    db.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (2, ?, ?)",
                   [(T0 + 100 + i, payload(100 + i, 100)) for i in range(5)])
    db.commit()
    crashed = tmp_path / "crashed"
    crashed.mkdir()
    for name in (path.name, path.name + "-wal"):
        shutil.copyfile(path.with_name(name), crashed / name)
    db.close()
    with pytest.raises(BagReadError, match="write-ahead log .* run `ipc-component bag recover` on the bag"):
        read(crashed / path.name)
    assert sorted(os.listdir(crashed)) == [path.name, path.name + "-wal"]
    assert recover_bag(crashed).readable
    messages = read(crashed)
    assert len(messages) == 15 and messages[-1] == ("/chatter", T0 + 104, payload(104, 100))
