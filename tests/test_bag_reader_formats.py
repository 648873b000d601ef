"""The bag reader on the layouts older rosbag2 releases wrote (metadata.yaml 4 to 9, SQLite3 schemas 2 to
4, MCAP with and without chunks, compression and summary, rosbag2_compression's FILE and MESSAGE modes),
written by tests/legacy_bags.py from rosbag2's sources; where ``rosbags`` reads them, it must read the
same.
"""
from __future__ import annotations

import logging
import random
import tempfile
from pathlib import Path
from typing import Any

import pytest
import yaml
from mcap.writer import CompressionType
from rosbags.rosbag2 import Reader

from baglib.format.metadata import parse_qos_profiles
from baglib.read.reader import BagReader
from legacy_bags import (
    LegacyMessage,
    LegacyTopic,
    compress_file,
    metadata_document,
    qos_text,
    write_mcap,
    write_metadata,
    write_sqlite,
)

T0 = 1_600_000_000_000_000_000
INFINITE = {"sec": 9223372036, "nsec": 854775807}
RELIABLE = {"history": "keep_last", "depth": 10, "reliability": "reliable", "durability": "volatile",
            "deadline": {"sec": 0, "nsec": 0}, "lifespan": {"sec": 0, "nsec": 0}, "liveliness": "automatic",
            "liveliness_lease_duration": {"sec": 0, "nsec": 0}, "avoid_ros_namespace_conventions": False}
LATCHED = {**RELIABLE, "history": "keep_all", "depth": 0, "durability": "transient_local",
           "reliability": "best_effort", "lifespan": {"sec": 10, "nsec": 500}, "deadline": INFINITE,
           "liveliness": "manual_by_topic", "liveliness_lease_duration": INFINITE}
TOPICS = [
    LegacyTopic("/chatter", "std_msgs/msg/String", [RELIABLE], "RIHS01_" + "ab" * 32),
    LegacyTopic("/rosout", "rcl_interfaces/msg/Log", [LATCHED, RELIABLE], "RIHS01_" + "cd" * 32,
                ("ros2msg", "uint8 level\n")),
    LegacyTopic("/unused", "std_msgs/msg/Empty", [], ""),
]


def messages(count: int, seed: int = 0) -> list[LegacyMessage]:
    """Log-time ordered messages (runs of equal times), publish time 5 ns earlier."""
    rng = random.Random(seed)
    return [("/chatter" if i % 3 else "/rosout", T0 + i // 2 * 100, T0 + i // 2 * 100 - 5,
             rng.randbytes(rng.randrange(4, 3000))) for i in range(count)]


def read(bag: Path, **filters: Any) -> list[tuple[str, int, int, bytes]]:
    with BagReader(bag) as reader:
        return [(m.connection.topic, m.log_time_ns, m.publish_time_ns, bytes(m.data))
                for m in reader.messages(**filters)]


def read_rosbags(bag: Path) -> list[tuple[str, int, bytes]]:
    with Reader(bag) as reader:
        return [(connection.topic, timestamp, bytes(data)) for connection, timestamp, data in reader.messages()]


def without_publish_time(stream: list[LegacyMessage]) -> list[tuple[str, int, int, bytes]]:
    return [(topic, log_time, log_time, data) for topic, log_time, _, data in stream]


def expected_topics(version: int, stream: list[LegacyMessage]
                    ) -> list[tuple[str, str, tuple[dict[str, Any], ...], str, int]]:
    return [(topic.name, topic.type, tuple(topic.qos), topic.type_hash if version >= 7 else "",
             sum(1 for message in stream if message[0] == topic.name)) for topic in TOPICS]


def check_connections(reader: BagReader, version: int, stream: list[LegacyMessage]) -> None:
    assert [(c.topic, c.msgtype, c.offered_qos_profiles, c.type_description_hash, c.message_count)
            for c in reader.connections] == expected_topics(version, stream)
    assert reader.message_count == len(stream)


# (metadata version, SQLite3 schema version, ROS distro) as rosbag2 wrote them together.
SQLITE_RELEASES = [(4, 2, "foxy"), (5, 2, "galactic"), (5, 3, "humble"), (6, 3, "humble"), (7, 4, "iron"),
                   (8, 4, "iron"), (9, 4, "jazzy")]


@pytest.mark.parametrize("release", SQLITE_RELEASES, ids=lambda r: f"v{r[0]}-schema{r[1]}-{r[2]}")
def test_sqlite3_bags_of_every_release(release: tuple[int, int, str], tmp_path: Path) -> None:
    version, schema, distro = release
    bag = tmp_path / "bag"
    bag.mkdir()
    parts = [messages(8, seed=1), messages(7, seed=2)]
    parts[1] = [(topic, log_time + 10_000, publish_time, data) for topic, log_time, publish_time, data in parts[1]]
    files = ["bag_0.db3", "bag_1.db3"]
    document = metadata_document(version, "sqlite3", files, TOPICS, parts, custom_data={"k": "v"},
                                 ros_distro=distro)
    for name, part in zip(files, parts, strict=True):
        write_sqlite(bag / name, schema, TOPICS, part, version, ros_distro=distro,
                     serialized_metadata=yaml.safe_dump(document))
    write_metadata(bag, document)
    stream = parts[0] + parts[1]
    with BagReader(bag) as reader:
        check_connections(reader, version, stream)
        assert reader.ros_distro == (distro if version >= 8 or schema >= 3 else "")
        assert reader.custom_data == ({"k": "v"} if version >= 6 else {})
        assert (reader.starting_time_ns, reader.end_time_ns) == (stream[0][1], stream[-1][1])
        definitions = [c.message_definition for c in reader.connections]
        assert definitions == ([t.definition for t in TOPICS] if schema >= 4 else [None] * 3)
    assert read(bag) == without_publish_time(stream)
    assert read(bag, topics=["/rosout"], start_ns=T0 + 200, stop_ns=T0 + 10_300) == [
        m for m in without_publish_time(stream) if m[0] == "/rosout" and T0 + 200 <= m[1] < T0 + 10_300]
    assert read_rosbags(bag) == [(topic, log_time, data) for topic, log_time, _, data in stream]
    with BagReader(bag / files[1]) as single:  # the file alone: its topics and counts from its tables
        assert [(c.topic, c.message_count) for c in single.connections] == [("/chatter", 4), ("/rosout", 3),
                                                                             ("/unused", 0)]
        assert single.connections[1].offered_qos_profiles == (LATCHED, RELIABLE)


# (metadata version, QoS version of the channel metadata, the rosbag2 metadata record) by release.
MCAP_RELEASES = [(5, 8, None, "humble"), (8, 8, {"ROS_DISTRO": "iron"}, "iron"), (9, 9, "serialized", "jazzy")]


@pytest.mark.parametrize("layout", [
    {"chunked": True, "compression": CompressionType.ZSTD},
    {"chunked": True, "compression": CompressionType.LZ4},
    {"chunked": True, "compression": CompressionType.NONE},
    {"chunked": False, "compression": CompressionType.NONE},
    {"chunked": True, "compression": CompressionType.LZ4, "summary": False},
    {"chunked": False, "compression": CompressionType.NONE, "summary": False},
], ids=lambda layout: "-".join(str(value).split(".")[-1] for value in layout.values()))
@pytest.mark.parametrize("release", MCAP_RELEASES, ids=lambda r: f"v{r[0]}-{r[3]}")
def test_mcap_bags_of_every_release_and_layout(release: tuple, layout: dict[str, Any], tmp_path: Path,
                                               caplog: pytest.LogCaptureFixture) -> None:
    version, qos_version, record, distro = release
    bag = tmp_path / "bag"
    bag.mkdir()
    stream = messages(15)
    document = metadata_document(version, "mcap", ["bag_0.mcap"], TOPICS, [stream], ros_distro=distro)
    if record == "serialized":
        record = {"serialized_metadata": yaml.safe_dump(document)}
    write_mcap(bag / "bag_0.mcap", TOPICS, stream, qos_version, rosbag2_metadata=record, type_hashes=version >= 7,
               **layout)
    write_metadata(bag, document)
    with caplog.at_level(logging.WARNING), BagReader(bag) as reader:
        check_connections(reader, version, stream)
        assert [c.message_definition for c in reader.connections] == [t.definition for t in TOPICS]
        assert reader.ros_distro == (distro if version >= 8 else "")
        assert read(bag) == [(topic, log_time, publish_time, data) for topic, log_time, publish_time, data in stream]
    assert not caplog.records  # a file without summary is complete, not damaged
    with BagReader(bag / "bag_0.mcap") as single:
        assert [(c.topic, c.offered_qos_profiles, c.message_count) for c in single.connections] == \
               [(t[0], t[2], t[4]) for t in expected_topics(version, stream)]
        assert single.ros_distro == (distro if record else "")
        assert (single.starting_time_ns, single.end_time_ns) == (stream[0][1], stream[-1][1])
    if layout.get("summary", True):
        assert read_rosbags(bag) == [(topic, log_time, data) for topic, log_time, _, data in stream]


def test_rosbag2_message_compression(tmp_path: Path) -> None:
    """A Foxy bag with ``compression_mode: MESSAGE``: every message's data is one zstd frame. Its
    metadata (version 4) names the files with the bag directory prefixed, as rosbag2 wrote them then."""
    bag = tmp_path / "compressed"
    bag.mkdir()
    parts = [messages(9, seed=3), [(t, log + 5_000, p, d) for t, log, p, d in messages(6, seed=4)]]
    for index, part in enumerate(parts):
        write_sqlite(bag / f"compressed_{index}.db3", 2, TOPICS, part, 4, compress_messages=True)
    write_metadata(bag, metadata_document(4, "sqlite3", ["compressed/compressed_0.db3", "compressed/compressed_1.db3"],
                                          TOPICS, parts, compression_mode="MESSAGE", compression_format="zstd"))
    stream = parts[0] + parts[1]
    assert read(bag) == without_publish_time(stream)
    assert read(bag, topics=["/chatter"], start_ns=T0 + 300) == [
        m for m in without_publish_time(stream) if m[0] == "/chatter" and m[1] >= T0 + 300]


def test_rosbag2_message_compression_read_from_the_file_alone(tmp_path: Path) -> None:
    """A Humble database keeps the bag's metadata in its ``metadata`` table: read alone, it is still
    known to hold compressed messages."""
    stream = messages(12, seed=5)
    document = metadata_document(5, "sqlite3", ["alone_0.db3"], TOPICS, [stream], compression_mode="MESSAGE",
                                 compression_format="zstd")
    path = tmp_path / "alone_0.db3"
    write_sqlite(path, 3, TOPICS, stream, 5, ros_distro="humble", serialized_metadata=yaml.safe_dump(document),
                 compress_messages=True)
    assert read(path) == without_publish_time(stream)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_rosbag2_file_compression(storage: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``compression_mode: FILE``: each storage file is ``<name>.zstd``; it is decompressed into a temporary
    directory, which closing the reader removes."""
    bag = tmp_path / "filecomp"
    bag.mkdir()
    parts = [messages(10, seed=6), [(t, log + 9_000, p, d) for t, log, p, d in messages(5, seed=7)]]
    extension = ".db3" if storage == "sqlite3" else ".mcap"
    names = []
    for index, part in enumerate(parts):
        path = bag / f"filecomp_{index}{extension}"
        if storage == "sqlite3":
            write_sqlite(path, 3, TOPICS, part, 5, ros_distro="humble")
        else:
            write_mcap(path, TOPICS, part, 8)
        names.append(compress_file(path).name)
    version = 4 if storage == "sqlite3" else 8
    listed = [f"filecomp/{name}" for name in names] if version == 4 else names  # Foxy's prefixed names
    write_metadata(bag, metadata_document(version, storage, listed, TOPICS, parts, compression_mode="FILE",
                                          compression_format="zstd"))
    stream = parts[0] + parts[1]
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temporary))
    with BagReader(bag) as reader:
        assert reader.files == [bag / name for name in names]
        (decompressed,) = temporary.iterdir()
        assert sorted(path.name for path in decompressed.iterdir()) == [name[:-5] for name in names]
        got = [(m.connection.topic, m.log_time_ns, bytes(m.data), m.file_index) for m in reader.messages()]
    assert list(temporary.iterdir()) == []
    publish = [(t, log, d) for t, log, _, d in stream]
    assert [m[:3] for m in got] == publish and [m[3] for m in got] == [0] * 10 + [1] * 5
    if version >= 5:
        assert read_rosbags(bag) == publish
    with BagReader(bag / names[0]) as single:  # one compressed file alone
        assert [m.log_time_ns for m in single.messages()] == [m[1] for m in stream[:10]]
    assert list(temporary.iterdir()) == []


def test_qos_profiles_of_every_version_read_as_version_9() -> None:
    foxy = [{**RELIABLE, "deadline": {"sec": 2147483647, "nsec": 4294967295},  # Fast DDS' infinite
             "lifespan": {"sec": 2147483647, "nsec": 2147483647},  # Connext's
             "liveliness_lease_duration": INFINITE}]  # Cyclone DDS'
    assert parse_qos_profiles(qos_text(foxy, 4)) == [
        {**RELIABLE, "deadline": INFINITE, "lifespan": INFINITE, "liveliness_lease_duration": INFINITE}]
    assert parse_qos_profiles(qos_text([LATCHED, RELIABLE], 8)) == [LATCHED, RELIABLE]
    assert parse_qos_profiles(qos_text([LATCHED], 9)) == parse_qos_profiles([LATCHED]) == [LATCHED]
    assert parse_qos_profiles("") == parse_qos_profiles(None) == []
    assert parse_qos_profiles([{**RELIABLE, "history": 7, "liveliness": 2}])[0]["history"] == "unknown"
    for bad in ("- [unclosed", "just text", [{"history": "keep_last"}], [{**RELIABLE, "depth": "deep"}],
                [{**RELIABLE, "deadline": 5}]):
        with pytest.raises(ValueError):
            parse_qos_profiles(bad)
