"""``ipc-component bag convert`` as users run it (``ros2 bag convert``): bags in rosbag2's own layouts (written
from rosbag2's sources by tests/legacy_bags.py, every SQLite3 schema and MCAP with and without chunks) and bags
of this project's writer go through the command; every output bag, and every split file on its own, is read
back by the independent reader ``rosbags``. No ROS graph is needed: the command reads and writes files only.
"""
from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from mcap.writer import CompressionType
from rosbags.rosbag2 import Reader
from std_msgs.msg import Int32, String

from baglib.format.cdr_fast import serialize
from baglib.format.message_definitions import message_definition, type_hash
from baglib.format.metadata import TopicInfo
from baglib.read.mcap_reader import McapReader
from baglib.tools.convert import ConvertError, convert_bags
from baglib.tools.convert_options import InputBag, OutputBag
from baglib.write.writer import BagWriter
from ipc_component.cli import main as cli_main
from legacy_bags import LegacyTopic, metadata_document, write_mcap, write_metadata, write_sqlite

CLI = str(Path(sys.executable).with_name("ipc-component"))
T0 = 1_700_000_000_000_000_000
MS = 1_000_000
STRING, INT32, EVENT = "std_msgs/msg/String", "std_msgs/msg/Int32", "std_srvs/srv/SetBool_Event"
RELIABLE = {"history": "keep_last", "depth": 10, "reliability": "reliable", "durability": "volatile",
            "deadline": {"sec": 0, "nsec": 0}, "lifespan": {"sec": 0, "nsec": 0}, "liveliness": "automatic",
            "liveliness_lease_duration": {"sec": 0, "nsec": 0}, "avoid_ros_namespace_conventions": False}

#: (topic, log time, data) as rosbags reads them.
Messages = list[tuple[str, int, bytes]]


def stream(count: int = 60) -> list[tuple[str, int, int, bytes]]:
    """Log-time ordered messages on /chatter, /count and /camera/_hidden (some at equal times); publish time
    3 ns earlier."""
    out = []
    for n in range(count):
        t = T0 + n // 2 * 5 * MS
        if n % 3 == 0:
            out.append(("/count", t, t - 3, bytes(serialize(Int32(data=n)))))
        elif n % 3 == 1:
            out.append(("/chatter", t, t - 3, bytes(serialize(String(data=f"message {n}")))))
        else:
            out.append(("/camera/_hidden", t, t - 3, bytes(serialize(String(data=f"hidden {n}")))))
    return out


TOPICS = [LegacyTopic(name, kind, [RELIABLE], type_hash(kind), message_definition(kind))
          for name, kind in (("/chatter", STRING), ("/count", INT32), ("/camera/_hidden", STRING))]


def rosbag2_bag(path: Path, storage: str, release: tuple[int, int, str], layout: dict[str, Any]) -> Path:
    """Two files in rosbag2's layout of ``release`` (metadata version, SQLite3 schema, distro)."""
    version, schema, distro = release
    messages = stream()
    parts = [messages[:25], messages[25:]]
    files = [f"{path.name}_{index}.{'db3' if storage == 'sqlite3' else 'mcap'}" for index in range(2)]
    path.mkdir()
    document = metadata_document(version, storage, files, TOPICS, parts, ros_distro=distro)
    for name, part in zip(files, parts):
        if storage == "sqlite3":
            write_sqlite(path / name, schema, TOPICS, part, version, ros_distro=distro)
        else:
            write_mcap(path / name, TOPICS, part, min(version, 9), type_hashes=version >= 7, **layout)
    write_metadata(path, document)
    return path


def writer_bag(path: Path, storage: str = "mcap", count: int = 60, **options: Any) -> Path:
    """A bag of this project's writer (the recorder's)."""
    with BagWriter(path, storage_id=storage, **options) as writer:
        for name, kind in (("/chatter", STRING), ("/count", INT32), ("/camera/_hidden", STRING),
                           ("/switch/_service_event", EVENT)):
            writer.add_topic(TopicInfo(name, kind))
        for topic, t, publish, data in stream(count):
            writer.write(topic, data, t, publish)
        writer.write("/switch/_service_event", b"\x00\x01\x00\x00event", T0 + 1, T0 + 1)
    return path


def read_rosbags(bag: Path) -> Messages:
    with Reader(bag) as reader:
        return [(connection.topic, t, bytes(data)) for connection, t, data in reader.messages()]


def convert(tmp_path: Path, inputs: list[Any], outputs: list[dict[str, Any]], input_options: list[dict] | None = None
            ) -> subprocess.CompletedProcess[str]:
    """Run ``ipc-component bag convert`` with ``-i`` per input (a path, or [path, storage id]), or with an
    ``--input-options`` file of ``input_options``: the command's own ``main`` in this process (the installed
    command in a process of its own is what :func:`test_refusals_name_what_is_wrong_and_leave_nothing` ends
    with), its output captured."""
    output_file = tmp_path / f"output{len(list(tmp_path.glob('output*.yaml')))}.yaml"
    output_file.write_text(yaml.safe_dump({"output_bags": outputs}))
    arguments = ["bag", "convert", "-o", str(output_file)]
    for each in inputs:
        arguments += ["-i", *map(str, each if isinstance(each, list) else [each])]
    if input_options is not None:
        input_file = tmp_path / "input.yaml"
        input_file.write_text(yaml.safe_dump({"input_bags": input_options}))
        arguments += ["--input-options", str(input_file)]
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        status = cli_main(arguments)
    return subprocess.CompletedProcess([CLI, *arguments], status, stdout.getvalue(), stderr.getvalue())


def each_file(bag: Path) -> Iterator[Path]:
    files = sorted(bag.glob("*.mcap")) + sorted(bag.glob("*.db3"))
    assert files, bag
    yield from sorted(files, key=lambda path: int(path.stem.rsplit("_", 1)[1]))


# --- the rosbag2 layouts, identical in messages ------------------------------------------------------------------
SQLITE_RELEASES = [(4, 2, "foxy"), (5, 3, "humble"), (9, 4, "jazzy")]
MCAP_LAYOUTS = [{"chunked": True, "compression": CompressionType.ZSTD},
                {"chunked": True, "compression": CompressionType.LZ4},
                {"chunked": False, "compression": CompressionType.NONE}]


@pytest.mark.parametrize("output_storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("source", [("sqlite3", release, {}) for release in SQLITE_RELEASES]
                         + [("mcap", (9, 0, "jazzy"), layout) for layout in MCAP_LAYOUTS]
                         + [("mcap", (5, 0, "humble"), MCAP_LAYOUTS[0])],
                         ids=lambda s: f"{s[0]}-v{s[1][0]}-{s[1][2]}-" + "-".join(str(v).split(".")[-1]
                                                                                 for v in s[2].values()))
def test_rosbag2_layouts_come_back_identical(source: tuple, output_storage: str, tmp_path: Path) -> None:
    storage, release, layout = source
    bag = rosbag2_bag(tmp_path / "bag", storage, release, layout)
    expected = read_rosbags(bag)
    assert len(expected) == 60
    done = convert(tmp_path, [bag], [{"uri": str(tmp_path / "out"), "storage_id": output_storage,
                                      "all_topics": True, "include_hidden_topics": True}])
    assert done.returncode == 0, done.stderr
    assert read_rosbags(tmp_path / "out") == expected
    with Reader(tmp_path / "out") as reader:
        assert {c.topic: (c.msgtype, c.ext.offered_qos_profiles[0].depth) for c in reader.connections} == {
            "/chatter": (STRING, 10), "/count": (INT32, 10), "/camera/_hidden": (STRING, 10)}
    # and back to the input's storage: still the same messages
    done = convert(tmp_path, [tmp_path / "out"], [{"uri": str(tmp_path / "back"), "storage_id": storage,
                                                   "all_topics": True, "include_hidden_topics": True}])
    assert done.returncode == 0, done.stderr
    assert read_rosbags(tmp_path / "back") == expected


def test_storage_change_keeps_publish_times_where_both_store_them(tmp_path: Path) -> None:
    bag = writer_bag(tmp_path / "bag", "mcap")
    outputs = [{"uri": str(tmp_path / "db"), "storage_id": "sqlite3", "all": True, "include_hidden_topics": True},
               {"uri": str(tmp_path / "mcap"), "storage_id": "mcap", "all": "true", "include_hidden_topics": "yes",
                "storage_preset_profile": "zstd_fast"}]
    done = convert(tmp_path, [[bag, "mcap"]], outputs)
    assert done.returncode == 0, done.stderr
    expected = read_rosbags(bag)
    assert read_rosbags(tmp_path / "db") == read_rosbags(tmp_path / "mcap") == expected
    from baglib.read.reader import BagReader
    with BagReader(tmp_path / "mcap") as reader:
        assert all(m.publish_time_ns == m.log_time_ns - 3 for m in reader.messages(["/chatter"]))


# --- several inputs: merged by log time --------------------------------------------------------------------------
def test_inputs_of_every_writer_merge_by_log_time(tmp_path: Path) -> None:
    rosbag2 = rosbag2_bag(tmp_path / "rosbag2", "sqlite3", (9, 4, "jazzy"), {})
    ours = tmp_path / "ours"
    with BagWriter(ours, max_bagfile_size=2000) as writer:
        writer.add_topic(TopicInfo("/other", INT32))
        for n in range(40):
            writer.write("/other", bytes(serialize(Int32(data=n))), T0 + n * 4 * MS + 1, T0 + n * 4 * MS + 1)
    done = convert(tmp_path, [rosbag2, ours], [{"uri": str(tmp_path / "out"), "all_topics": True,
                                                "max_bagfile_size": 3000}])
    assert done.returncode == 0, done.stderr
    merged = read_rosbags(tmp_path / "out")
    expected = [m for m in read_rosbags(rosbag2) if m[0] != "/camera/_hidden"] + read_rosbags(ours)
    assert merged == sorted(expected, key=lambda m: m[1])  # sorted() is stable: input order at equal times
    assert len(list(each_file(tmp_path / "out"))) > 1


# --- filters, split, several outputs in one pass -----------------------------------------------------------------
FILTERS = [
    ({"topics": ["chatter"]}, {"/chatter"}),
    ({"regex": "^/c"}, {"/chatter", "/count"}),
    ({"all_topics": True, "exclude_regex": "count"}, {"/chatter"}),
    ({"all_topics": True, "exclude": "chatter"}, {"/count"}),
    ({"all_topics": True, "exclude_topics": ["/count"], "include_hidden_topics": True},
     {"/chatter", "/camera/_hidden"}),
    ({"topic_types": [INT32]}, {"/count"}),
    ({"topics": ["/camera/_hidden"]}, {"/camera/_hidden"}),
    ({"all_services": True}, {"/switch/_service_event"}),
    ({"services": ["/switch"], "topics": ["/count"]}, {"/switch/_service_event", "/count"}),
    ({"all": True, "exclude_services": ["switch"], "exclude_topic_types": [STRING]}, {"/count"}),
]


def test_filters_of_several_outputs_in_one_pass(tmp_path: Path) -> None:
    bag = writer_bag(tmp_path / "bag", "sqlite3")
    everything = read_rosbags(bag)
    outputs = [{"uri": str(tmp_path / f"out{index}"), **options} for index, (options, _) in enumerate(FILTERS)]
    done = convert(tmp_path, [bag], outputs)
    assert done.returncode == 0, done.stderr
    for index, (options, topics) in enumerate(FILTERS):
        assert read_rosbags(tmp_path / f"out{index}") == [m for m in everything if m[0] in topics], options


#: Split sizes that cut the bag into a few files: an MCAP file carries ~4 kB of schemas and summary, an empty
#: SQLite3 file ~20 kB (a smaller limit would split after nearly every message, one file each).
SPLIT_SIZES = {"mcap": 8000, "sqlite3": 32000}


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("split", ["max_bagfile_size", "max_bagfile_duration"])
def test_split_files_each_read_alone(storage: str, split: str, tmp_path: Path) -> None:
    bag = writer_bag(tmp_path / "bag", count=900)
    limit = SPLIT_SIZES[storage] if split == "max_bagfile_size" else 1
    done = convert(tmp_path, [bag], [{"uri": str(tmp_path / "out"), "storage_id": storage, "all_topics": True,
                                      split: limit}])
    assert done.returncode == 0, done.stderr
    files = list(each_file(tmp_path / "out"))
    assert 1 < len(files) < 30, len(files)
    parts = [read_rosbags(path) for path in files]  # each file alone, without metadata.yaml
    assert all(parts)
    assert [m for part in parts for m in part] == read_rosbags(tmp_path / "out") == \
           [m for m in read_rosbags(bag) if m[0] in ("/chatter", "/count")]


# --- time windows -------------------------------------------------------------------------------------------------
def test_time_windows_of_outputs_and_inputs_include_both_ends(tmp_path: Path) -> None:
    first, second = writer_bag(tmp_path / "first"), writer_bag(tmp_path / "second", "sqlite3")
    everything = sorted(read_rosbags(first) + read_rosbags(second), key=lambda m: m[1])
    start, end = T0 + 20 * MS, T0 + 60 * MS
    done = convert(tmp_path, [first, second], [{"uri": str(tmp_path / "cut"), "all": True,
                                                "start_time_ns": start, "end_time_ns": end},
                                               {"uri": str(tmp_path / "whole"), "all": True}])
    assert done.returncode == 0, done.stderr
    assert read_rosbags(tmp_path / "cut") == [m for m in everything if start <= m[1] <= end
                                              and m[0] != "/camera/_hidden"]
    assert read_rosbags(tmp_path / "whole") == [m for m in everything if m[0] != "/camera/_hidden"]
    # rosbag2 Lyrical's input windows: each input its own, the outputs take what is read
    done = convert(tmp_path, [], [{"uri": str(tmp_path / "windows"), "topics": ["/chatter"]}],
                   input_options=[{"uri": str(first), "start_time_ns": end},
                                  {"uri": str(second), "storage_id": "sqlite3", "end_time_ns": start}])
    assert done.returncode == 0, done.stderr
    assert read_rosbags(tmp_path / "windows") == sorted(
        [m for m in read_rosbags(first) if m[0] == "/chatter" and m[1] >= end]
        + [m for m in read_rosbags(second) if m[0] == "/chatter" and m[1] <= start], key=lambda m: m[1])


class CountingReads:
    """Counts the bytes the MCAP reader reads for messages (its positioned reads of chunks and records)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.bytes = self.reads = 0
        original = McapReader._pread

        def counted(reader: McapReader, length: int, offset: int) -> bytes:
            self.bytes += length
            self.reads += 1
            return original(reader, length, offset)
        monkeypatch.setattr(McapReader, "_pread", counted)


def test_a_cut_reads_only_the_chunks_it_needs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    frame = os.urandom(64 * 1024)
    with BagWriter(tmp_path / "bag") as writer:  # 20 MB in chunks of 768 KiB: about 27 chunks
        writer.add_topic(TopicInfo("/frames", "sensor_msgs/msg/Image"))
        for n in range(320):
            writer.write("/frames", n.to_bytes(4, "little") + frame, T0 + n * MS, T0 + n * MS)
    size = sum(path.stat().st_size for path in each_file(tmp_path / "bag"))
    whole, cut = CountingReads(monkeypatch), None
    convert_bags([InputBag(str(tmp_path / "bag"))], [OutputBag(str(tmp_path / "whole"), all_topics=True)])
    assert whole.bytes > 0.95 * size and whole.reads > 20
    for name, inputs, outputs in [  # the last tenth, by the input's window and by the output's
            ("input", [InputBag(str(tmp_path / "bag"), start_time_ns=T0 + 288 * MS)],
             [OutputBag(str(tmp_path / "input"), all_topics=True)]),
            ("output", [InputBag(str(tmp_path / "bag"))],
             [OutputBag(str(tmp_path / "output"), all_topics=True, start_time_ns=T0 + 288 * MS)])]:
        cut = CountingReads(monkeypatch)
        report = convert_bags(inputs, outputs)
        assert report.outputs[0][2] == 32
        assert cut.bytes < 0.2 * whole.bytes, (name, cut.bytes, whole.bytes)
        assert read_rosbags(tmp_path / name) == read_rosbags(tmp_path / "whole")[288:]


def peak_rss_of_convert(bag: Path, output: Path) -> int:
    """Peak RSS (KiB) of a fresh process that converts ``bag`` into ``output`` (SQLite3)."""
    code = ("import resource, sys; from baglib.tools.convert import convert_bags; "
            "from baglib.tools.convert_options import InputBag, OutputBag; "
            "convert_bags([InputBag(sys.argv[1])], [OutputBag(sys.argv[2], 'sqlite3', all_topics=True)]); "
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    done = subprocess.run([sys.executable, "-c", code, str(bag), str(output)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    return int(done.stdout)


def test_memory_does_not_grow_with_the_bag(tmp_path: Path) -> None:
    frame = bytearray(os.urandom(256 * 1024))
    rss = []
    for megabytes in (20, 120):
        with BagWriter(tmp_path / f"in{megabytes}") as writer:
            writer.add_topic(TopicInfo("/frames", "sensor_msgs/msg/Image"))
            for n in range(megabytes * 4):
                frame[:8] = n.to_bytes(8, "little")
                writer.write("/frames", bytes(frame), T0 + n * 10 * MS, T0 + n * 10 * MS)
        rss.append(peak_rss_of_convert(tmp_path / f"in{megabytes}", tmp_path / f"out{megabytes}"))
    # the bag grew by 100 MB; a conversion that held messages would grow with it
    assert rss[1] - rss[0] < 30 * 1024, rss


# --- bad input: a clear error, nothing left behind ------------------------------------------------------------
def test_refusals_name_what_is_wrong_and_leave_nothing(tmp_path: Path) -> None:
    bag = writer_bag(tmp_path / "bag")
    out = str(tmp_path / "out")
    end = T0 + 29 * 5 * MS
    cases: list[tuple[list[Any], list[dict[str, Any]], list[dict] | None, list[str]]] = [
        ([bag], [{"uri": out, "all_topics": True, "stop_time_ns": T0}], None,
         ["output_bags[0]", "unknown key 'stop_time_ns'"]),
        ([], [{"uri": out, "all_topics": True}], [{"uri": str(bag), "max_bagfile_size": 10}],
         ["input_bags[0]", "unknown key 'max_bagfile_size'"]),
        ([bag], [{"uri": out, "all_topics": True, "start_time_ns": end + 1}], None,
         [out, "holds no message of the inputs", str(end)]),
        ([], [{"uri": out, "all_topics": True}], [{"uri": str(bag), "end_time_ns": T0 - 1}],
         [str(bag), "holds no message of the bag", str(T0)]),
        ([bag], [{"uri": out, "all_topics": True, "start_time_ns": T0 + 10, "end_time_ns": T0}], None,
         ["start_time_ns", "is after end_time_ns"]),
        ([tmp_path / "missing"], [{"uri": out, "all_topics": True}], None,
         [str(tmp_path / "missing"), "does not exist"]),
        ([bag], [{"uri": out, "all_topics": True, "compression_mode": "file", "compression_format": "zstd"}], None,
         ["compression_mode is not supported", "zstd_fast"]),
        ([bag], [{"uri": out, "topics": ["/nothing"]}], None, [out, "selects none"]),
        ([bag], [{"uri": out, "all_topics": True, "storage_id": "rosbag_v1"}], None, ["rosbag_v1"]),
        ([bag], [{"uri": out, "all_topics": True}, {"uri": str(bag / "metadata.yaml" / "x"), "all_topics": True}],
         None, ["no output kept", "metadata.yaml"]),
        ([bag], [{"uri": out, "all_topics": True}, {"uri": out, "all_topics": True}], None, ["named twice"]),
        ([bag], [{"uri": str(bag), "all_topics": True}], None, ["already exists"]),
        ([bag], [{"uri": out, "all_topics": "maybe"}], None, ["all_topics must be true or false"]),
        ([bag], [{"uri": out, "regex": "("}], None, [out, "missing )"]),
        ([bag], [{"uri": out, "all_topics": True}], [{"uri": str(bag)}], ["not both"]),
    ]
    for inputs, outputs, input_options, needles in cases:
        done = convert(tmp_path, inputs, outputs, input_options)
        assert done.returncode == 1, (needles, done.stdout)
        assert all(needle in done.stderr for needle in needles), (needles, done.stderr)
        assert not Path(out).exists(), needles
    unknown_top = tmp_path / "top.yaml"
    unknown_top.write_text(yaml.safe_dump({"output_bags": [{"uri": out, "all_topics": True}], "outputs": []}))
    done = subprocess.run([CLI, "bag", "convert", "-i", str(bag), "-o", str(unknown_top)], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 1 and "unknown top-level key 'outputs'" in done.stderr and not Path(out).exists()


def test_an_unfinished_input_is_refused_with_the_recover_command(tmp_path: Path) -> None:
    bag = writer_bag(tmp_path / "bag")
    (bag / "metadata.yaml").unlink()
    with pytest.raises(ConvertError, match="bag recover"):
        convert_bags([InputBag(str(bag))], [OutputBag(str(tmp_path / "out"), all_topics=True)])
    assert not (tmp_path / "out").exists()


def test_names_stored_without_their_slash_come_out_fully_qualified(tmp_path: Path) -> None:
    """rosbag2 stores a name as the node gave it; its own test bags (rosbag2_py's ``wbag``, ``convert_a``) hold
    ``HHH`` and ``a_empty``. The output names the topic the messages were published on."""
    topics = [LegacyTopic("chatter", STRING, [RELIABLE], type_hash(STRING), message_definition(STRING))]
    messages = [("chatter", T0 + n * MS, T0 + n * MS, bytes(serialize(String(data=f"m{n}")))) for n in range(10)]
    bag = tmp_path / "bag"
    bag.mkdir()
    write_mcap(bag / "bag_0.mcap", topics, messages, 9)
    write_metadata(bag, metadata_document(9, "mcap", ["bag_0.mcap"], topics, [messages], ros_distro="jazzy"))
    done = convert(tmp_path, [bag], [{"uri": str(tmp_path / "out"), "topics": ["chatter"]},
                                     {"uri": str(tmp_path / "db"), "storage_id": "sqlite3", "regex": "^/chat"}])
    assert done.returncode == 0, done.stderr
    expected = [("/chatter", t, data) for _, t, _, data in messages]
    assert read_rosbags(tmp_path / "out") == read_rosbags(tmp_path / "db") == expected
