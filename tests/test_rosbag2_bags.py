"""Bags rosbag2 itself wrote (``tests/data/rosbag2``, listed with their origin in its README) through
``ipc-component bag convert`` (the command's own ``main``, in this process): each comes back identical in
messages in either storage, as the independent reader ``rosbags`` reads it (and ``mcap``'s reader, for the
publish times only MCAP keeps).

Identical means: the same topics (names fully qualified, as convert writes them) of the same types
(``pkg/msg/T``), as many messages on each as the bag's metadata states, and per topic the same log times and
serialized bytes in the same order; where the output is MCAP, the same publish times (an SQLite3 input has
none: its log times stand in, as rosbag2's reader gives them).

The vendored bags' types are either recorded in the bag or installed here (``test_msgs`` is a test
dependency). The case rosbag2's ``bag_rewrite`` covers with an empty definition, a type neither recorded nor
installed, is therefore written in rosbag2's own layouts by tests/legacy_bags.py, with a package that exists
nowhere.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader
from rosbags.interfaces import MessageDefinitionFormat
from rosbags.rosbag2 import Reader
from std_msgs.msg import String

from baglib.format.cdr_fast import serialize
from baglib.format.message_definitions import message_definition, type_hash
from legacy_bags import LegacyTopic, metadata_document, write_mcap, write_metadata, write_sqlite
from test_bag_convert import convert, each_file

DATA = Path(__file__).with_name("data") / "rosbag2"
#: Every vendored bag: the directories with a metadata.yaml, and the single storage files.
BAGS = sorted([path.parent for path in DATA.glob("*/*/metadata.yaml")] + list((DATA / "files").iterdir()))
STORAGES = ["mcap", "sqlite3"]

#: Per topic: its type and its messages as (log time, bytes), in the reader's order.
Content = dict[str, tuple[str, list[tuple[int, bytes]]]]


def full_name(topic: str) -> str:
    return topic if topic.startswith("/") else f"/{topic}"


def full_type(msgtype: str) -> str:
    """``pkg/T`` (rosbag2 before Foxy) as ``pkg/msg/T``."""
    package, *rest = msgtype.split("/")
    return "/".join([package, "msg", *rest]) if len(rest) == 1 else msgtype


def read(path: Path) -> Content:
    """What rosbags reads from ``path`` (a bag directory or one storage file); the message count it states per
    topic must be what it holds."""
    topics: Content = {}
    stated: dict[str, int] = {}
    with Reader(path) as reader:
        for connection in reader.connections:
            name = full_name(connection.topic)
            assert topics.setdefault(name, (full_type(connection.msgtype), []))[0] == full_type(connection.msgtype)
            stated[name] = stated.get(name, 0) + connection.msgcount
        for connection, log_time, data in reader.messages():
            topics[full_name(connection.topic)][1].append((log_time, bytes(data)))
    assert stated == {name: len(messages) for name, (_, messages) in topics.items()}
    return topics


def content(bag: Path) -> Content:
    """``bag`` read file by file with rosbags, each file's messages after the previous one's. File by file because
    rosbags matches a directory's files to its metadata.yaml by the QoS profiles too, and in rosbag2's older
    bags the two disagree (``history: 3`` in the metadata): rosbags then yields no message at all. The counts
    metadata.yaml states must still be what the files hold."""
    document = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"] \
        if bag.is_dir() else None
    topics: Content = {}
    for path in [bag / name for name in document["relative_file_paths"]] if document else [bag]:
        for name, (kind, messages) in read(path).items():
            topics.setdefault(name, (kind, []))[1].extend(messages)
    if document:
        assert {full_name(entry["topic_metadata"]["name"]): entry["message_count"]
                for entry in document["topics_with_message_count"]} == {
            name: len(messages) for name, (_, messages) in topics.items()}
    return topics


def times(bag: Path) -> list[tuple[str, int, int, bytes]]:
    """Every message as (topic, log time, publish time, bytes), sorted: from the MCAP files with ``mcap``'s reader,
    from SQLite3 (no publish time) with rosbags and the log time twice."""
    files = sorted(bag.glob("*.mcap")) if bag.is_dir() else [bag] if bag.suffix == ".mcap" else []
    if files:
        found = []
        for path in files:
            with path.open("rb") as stream:
                found += [(full_name(channel.topic), message.log_time, message.publish_time, message.data)
                          for _, channel, message in make_reader(stream).iter_messages(log_time_order=False)]
        return sorted(found)
    return sorted((name, log_time, log_time, data) for name, (_, messages) in content(bag).items()
                  for log_time, data in messages)


def copied(bag: Path, tmp_path: Path) -> Path:
    """A copy of the vendored ``bag`` to read: reading a WAL-mode database the ordinary way (rosbags) puts side
    files next to it, and the source tree stays as it is."""
    target = tmp_path / "input" / bag.name
    target.parent.mkdir()
    (shutil.copytree if bag.is_dir() else shutil.copyfile)(bag, target)
    return target


def run(tmp_path: Path, bag: Path, output: dict) -> str:
    """Convert ``bag`` into ``tmp_path/out`` (all topics, hidden ones too) with ``output``'s options; stderr."""
    done = convert(tmp_path, [bag], [{"uri": str(tmp_path / "out"), "all_topics": True, "all_services": True,
                                      "include_hidden_topics": True, **output}])
    assert done.returncode == 0, done.stderr
    return done.stderr


@pytest.mark.parametrize("storage", STORAGES)
@pytest.mark.parametrize("bag", BAGS, ids=lambda path: str(path.relative_to(DATA)))
def test_bags_rosbag2_wrote_come_back_identical(bag: Path, storage: str, tmp_path: Path) -> None:
    bag = copied(bag, tmp_path)
    expected = content(bag)
    assert run(tmp_path, bag, {"storage_id": storage}) == ""  # no warning: every type is described
    assert content(tmp_path / "out") == read(tmp_path / "out") == expected
    if storage == "mcap":
        assert times(tmp_path / "out") == times(bag)


@pytest.mark.parametrize("storage, size", [("mcap", 40_000), ("sqlite3", 120_000)])
def test_a_split_bag_split_again_reads_file_by_file(storage: str, size: int, tmp_path: Path) -> None:
    """rosbag2's five-file MCAP bag (6074 messages) into files of ``size`` bytes: each file, read on its own,
    holds messages, and one after the other they are the bag's."""
    bag = copied(DATA / "mcap" / "wbag", tmp_path)
    run(tmp_path, bag, {"storage_id": storage, "max_bagfile_size": size})
    files = list(each_file(tmp_path / "out"))
    assert 2 < len(files) < 20, files
    assert all(any(messages for _, messages in read(path).values()) for path in files)
    assert content(tmp_path / "out") == read(tmp_path / "out") == content(bag)


def test_service_event_definitions_rosbag2_keys_by_service_type_are_kept(tmp_path: Path) -> None:
    """rosbag2's SQLite3 storage keys a service event type's definition by the service type
    (``example_interfaces/srv/AddTwoInts``, not ``..._Event``); ``example_interfaces`` is not installed here, so
    the bag's own text is the only description there is, and the converted bag carries it."""
    bag = copied(DATA / "files" / "topics_and_services.db3", tmp_path)
    run(tmp_path, bag, {"storage_id": "mcap"})
    with Reader(tmp_path / "out") as reader:
        events = [c for c in reader.connections if c.msgtype == "example_interfaces/srv/AddTwoInts_Event"]
        assert len(events) == 2
        assert {(c.msgdef.format, c.msgdef.data) for c in events} == {
            (MessageDefinitionFormat.MSG, "int64 a\nint64 b\n---\nint64 sum\n")}


# --- a type nobody describes -------------------------------------------------------------------------------------
T0 = 1_700_000_000_000_000_000
THING = "not_installed_msgs/msg/Thing"
STRING = "std_msgs/msg/String"


def undescribed_bag(path: Path, storage: str, schema: int) -> list[tuple[str, int, int, bytes]]:
    """A bag as rosbag2 writes one with a type it cannot find (``SequentialWriter::create_topic``: an empty
    definition): Jazzy's MCAP (a schema without encoding or text) or SQLite3 schema 4 (a message_definitions row
    likewise), or Humble's SQLite3 schema 3 (no definitions at all). Its messages, written."""
    topics = [LegacyTopic("/thing", THING, definition=("", "")),
              LegacyTopic("/chatter", STRING, type_hash=type_hash(STRING), definition=message_definition(STRING))]
    messages = [("/thing" if n % 2 else "/chatter", T0 + n * 1000, T0 + n * 1000 - 7,
                 bytes(serialize(String(data=f"hello {n}"))) if n % 2 == 0 else bytes([0, 1, 0, 0, n, 0, 0, 0]))
                for n in range(20)]
    legacy_bag(path, storage, schema, topics, messages)
    return messages


def legacy_bag(path: Path, storage: str, schema: int, topics: list[LegacyTopic],
               messages: list[tuple[str, int, int, bytes]]) -> None:
    """One file in rosbag2's layout: Jazzy's MCAP or SQLite3 ``schema`` 4 (metadata version 9), or Humble's
    SQLite3 schema 3 (metadata version 5)."""
    path.mkdir()
    name = f"{path.name}_0.{'mcap' if storage == 'mcap' else 'db3'}"
    version = 9 if schema == 4 else 5
    if storage == "mcap":
        write_mcap(path / name, topics, messages, version)
    else:
        write_sqlite(path / name, schema, topics, messages, version)
    write_metadata(path, metadata_document(version, storage, [name], topics, [messages]))


@pytest.mark.parametrize("storage", STORAGES)
@pytest.mark.parametrize("source", [("mcap", 4), ("sqlite3", 4), ("sqlite3", 3)], ids=lambda s: f"{s[0]}-{s[1]}")
def test_a_type_nobody_describes_is_copied_with_a_warning(source: tuple[str, int], storage: str,
                                                         tmp_path: Path) -> None:
    """As rosbag2's ``bag_rewrite``: the messages are copied unchanged, the type is described with rosbag2's
    empty definition, and the command warns, naming the type and its topic. The output converts again."""
    messages = undescribed_bag(tmp_path / "bag", *source)
    warning = run(tmp_path, tmp_path / "bag", {"storage_id": storage})
    assert "warning" in warning and THING in warning and "/thing" in warning and STRING not in warning, warning
    expected = {"/thing": (THING, [(t, data) for topic, t, _, data in messages if topic == "/thing"]),
                "/chatter": (STRING, [(t, data) for topic, t, _, data in messages if topic == "/chatter"])}
    assert content(tmp_path / "out") == expected
    with Reader(tmp_path / "out") as reader:
        assert {c.topic: c.msgdef.format for c in reader.connections} == {
            "/thing": MessageDefinitionFormat.NONE, "/chatter": MessageDefinitionFormat.MSG}
    if storage == "mcap":
        assert times(tmp_path / "out") == sorted(
            (topic, t, t if source[0] == "sqlite3" else publish, data) for topic, t, publish, data in messages)
    again = tmp_path / "again"
    again.mkdir()
    assert THING in run(again, tmp_path / "out", {"storage_id": "sqlite3" if storage == "mcap" else "mcap"})
    assert content(again / "out") == expected


@pytest.mark.parametrize("storage", STORAGES)
def test_an_empty_message_type_keeps_its_recorded_empty_definition(storage: str, tmp_path: Path) -> None:
    """A message without fields has an empty definition text (``test_msgs/msg/Empty`` in rosbag2's
    ``convert_a`` bag); recorded with its encoding, it is a definition like any other, also where the type is not
    installed: no warning, and the output records it."""
    nothing = LegacyTopic("/nothing", "not_installed_msgs/msg/Nothing", definition=("ros2msg", ""))
    messages = [("/nothing", T0 + n, T0 + n, b"\0\1\0\0\0\0\0\0") for n in range(3)]
    bag = tmp_path / "bag"
    legacy_bag(bag, storage, 4, [nothing], messages)
    assert run(tmp_path, bag, {"storage_id": "sqlite3" if storage == "mcap" else "mcap"}) == ""
    with Reader(tmp_path / "out") as reader:
        assert [(c.msgdef.format, c.msgdef.data) for c in reader.connections] == [(MessageDefinitionFormat.MSG, "")]
    assert content(tmp_path / "out") == {"/nothing": (nothing.type, [(t, data) for _, t, _, data in messages])}
