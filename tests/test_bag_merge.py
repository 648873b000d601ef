"""``ipc-component bag merge`` as users run it: real bags of several writers in, one bag out, read back by the
independent readers (``rosbags``, and the ``mcap`` reader with ``mcap-ros2-support``'s decoder).

The inputs are what a fleet session meets: a bag in rosbag2's own layout (split into two files, written from
rosbag2's sources by tests/legacy_bags.py), bags written by ``rosbags`` (MCAP and SQLite3), and bags of this
project's recorder writer (split, with the fleet keys in ``custom_data``). No ROS graph is needed: the command
reads and writes files only.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rcl_interfaces.msg import Log
from rclpy.node import Node
from std_msgs.msg import Int32, String

from baglib.format import fleet_keys
from baglib.format.cdr_fast import serialize
from baglib.format.message_definitions import message_definition, type_hash
from baglib.format.metadata import TopicInfo
from baglib.write.writer import BagWriter
from ipc_testing import ContainerClient, ContainerProcess, wait_until
from legacy_bags import LegacyTopic, metadata_document, write_mcap, write_metadata, write_sqlite

CLI = str(Path(sys.executable).with_name("ipc-component"))
REPO = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000
MS = 1_000_000
TIE = T0 + 10_000 * MS  # every input has a message at this time: the merge keeps input order
STRING, INT32 = "std_msgs/msg/String", "std_msgs/msg/Int32"

#: (topic, log time, CDR) of one input, in the input's own order.
Plan = list[tuple[str, int, bytes]]


def chatter(label: str) -> bytes:
    return bytes(serialize(String(data=label)))


def count(value: int) -> bytes:
    return bytes(serialize(Int32(data=value)))


def plan_of(index: int, own_topic: str, messages: int = 40) -> Plan:
    """Input ``index``: /chatter (shared by all inputs) every 4 ms, shifted by ``index`` ms, and its own Int32
    topic every fifth message; one /chatter message at TIE."""
    plan: Plan = []
    for n in range(messages):
        t = T0 + n * 4 * MS + index * MS
        plan.append(("/chatter", t, chatter(f"input {index} message {n}")))
        if n % 5 == 0:
            plan.append((own_topic, t, count(100 * index + n)))
    plan.append(("/chatter", TIE, chatter(f"input {index} at the tie")))
    return plan


# --- inputs of each writer ---------------------------------------------------------------------------------
def rosbag2_layout(path: Path, plan: Plan) -> Path:
    """rosbag2's own layout (metadata.yaml version 9, two MCAP files as rosbag2_storage_mcap writes them)."""
    topics = [LegacyTopic(name, kind, type_hash=type_hash(kind), definition=message_definition(kind))
              for name, kind in (("/chatter", STRING), (own_topic(plan), INT32))]
    messages = [(topic, t, t, data) for topic, t, data in plan]
    half = len(messages) // 2
    parts, files = [messages[:half], messages[half:]], [f"{path.name}_0.mcap", f"{path.name}_1.mcap"]
    path.mkdir()
    for name, part in zip(files, parts):
        write_mcap(path / name, topics, part, 9)
    write_metadata(path, metadata_document(9, "mcap", files, topics, parts, ros_distro="jazzy"))
    return path


def rosbags_bag(path: Path, plan: Plan, storage: str) -> Path:
    """Written by ``rosbags``' own writer."""
    store = get_typestore(Stores.ROS2_JAZZY)
    with Writer(path, version=9, storage_plugin=StoragePlugin[storage]) as writer:
        connections = {topic: writer.add_connection(topic, STRING if topic == "/chatter" else INT32,
                                                    typestore=store) for topic in dict.fromkeys(t for t, _, _ in plan)}
        for topic, t, data in plan:
            writer.write(connections[topic], t, data)
    return path


def recorder_bag(path: Path, plan: Plan, custom_data: dict[str, str] | None = None, storage_id: str = "mcap"
                 ) -> Path:
    """Written by this project's recorder writer, split into several files."""
    with BagWriter(path, storage_id=storage_id, max_bagfile_size=3000, custom_data=custom_data) as writer:
        for topic in dict.fromkeys(t for t, _, _ in plan):
            writer.add_topic(TopicInfo(topic, STRING if topic == "/chatter" else INT32))
        for topic, t, data in plan:
            writer.write(topic, data, t, t)
    assert len(list(path.glob("*.mcap" if storage_id == "mcap" else "*.db3"))) > 1
    return path


def own_topic(plan: Plan) -> str:
    return next(topic for topic, _, _ in plan if topic != "/chatter")


def fleet(host: str, offset_ns: int = 0) -> dict[str, str]:
    return {fleet_keys.SESSION: "s1", fleet_keys.HOST: host, fleet_keys.CONTAINER: "main",
            fleet_keys.START_NS: str(T0), fleet_keys.STOP_NS: "", fleet_keys.CLOCK_OFFSET_NS: str(offset_ns),
            fleet_keys.CLOCK_OFFSET_UNCERTAINTY_NS: "20000"}


def four_inputs(root: Path) -> tuple[list[Path], list[Plan]]:
    plans = [plan_of(index, f"/count{index}") for index in range(4)]
    bags = [rosbag2_layout(root / "robot_a", plans[0]),
            rosbags_bag(root / "rosbags_mcap", plans[1], "MCAP"),
            rosbags_bag(root / "rosbags_sqlite", plans[2], "SQLITE3"),
            recorder_bag(root / "ours", plans[3], fleet("cam-host.local"))]
    return bags, plans


def merged_order(plans: list[Plan], rename: Any = lambda index, topic: topic) -> Plan:
    """What the merged bag holds, in order: by log time, equal times in input order (a stable sort)."""
    tagged = [(rename(index, topic), t, data) for index, plan in enumerate(plans) for topic, t, data in plan]
    return sorted(tagged, key=lambda message: message[1])


# --- reading the result back --------------------------------------------------------------------------------
def rosbags_messages(bag: Path) -> Plan:
    with Reader(bag) as reader:
        return [(connection.topic, t, bytes(data)) for connection, t, data in reader.messages()]


def mcap_messages(bag: Path) -> Plan:
    """Every message of every MCAP file in file order, each decoded by mcap-ros2-support to check it parses."""
    messages: Plan = []
    for path in sorted(bag.glob("*.mcap")):
        with open(path, "rb") as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
                assert decoded.data is not None
                messages.append((channel.topic, message.log_time, message.data))
    return messages


def sqlite_messages(bag: Path) -> Plan:
    """Every row of the database in insertion order."""
    (path,) = bag.glob("*.db3")
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
        return [(topic, t, bytes(data)) for topic, t, data in db.execute(
            "SELECT topics.name, timestamp, data FROM messages JOIN topics ON topics.id = topic_id ORDER BY messages.id")]


def metadata(bag: Path) -> dict[str, Any]:
    return yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def merge(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([CLI, "bag", "merge", *map(str, args)], capture_output=True, text=True, timeout=120)


def tree_digest(root: Path) -> dict[str, tuple[str, int]]:
    """Every file under ``root``: its content's hash and its modification time."""
    return {str(path.relative_to(root)): (hashlib.sha256(path.read_bytes()).hexdigest(), path.stat().st_mtime_ns)
            for path in sorted(root.rglob("*")) if path.is_file()}


# --- tests ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_merges_bags_of_every_writer_in_log_time_order(tmp_path: Path, storage: str) -> None:
    bags, plans = four_inputs(tmp_path)
    done = merge(tmp_path / "merged", *bags, "-s", storage)
    assert done.returncode == 0, done.stderr
    assert "Merged 4 bags" in done.stdout and f"{sum(map(len, plans))} messages on 5 topics" in done.stdout
    expected = merged_order(plans)
    merged = tmp_path / "merged"
    # the storage holds them in merged order; each independent reader finds every message once, intact
    assert (mcap_messages(merged) if storage == "mcap" else sqlite_messages(merged)) == expected
    assert rosbags_messages(merged) == expected
    tie = [data for _, t, data in expected if t == TIE]
    assert tie == [chatter(f"input {index} at the tie") for index in range(4)]
    info = metadata(merged)
    counts = {entry["topic_metadata"]["name"]: entry["message_count"] for entry in info["topics_with_message_count"]}
    assert counts == {"/chatter": 4 * 41, **{f"/count{index}": 8 for index in range(4)}}
    assert info["starting_time"]["nanoseconds_since_epoch"] == T0 and info["message_count"] == len(expected)


def record_fleet_bag(probe: Node, session: Path, host: str, count: int) -> Path:
    """One computer of a fleet session: a container with a talker on /<host>/chatter and a recorder of that topic
    next to it (intra-process), recording into ``session/<host>_main`` with the fleet keys, until ``count``
    messages went out; the recorder is unloaded (the bag finalized) and the container stopped."""
    bag = session / f"{host}_main"
    heard: list[String] = []
    subscription = probe.create_subscription(String, f"/{host}/chatter", heard.append, 100)
    with ContainerProcess("--use-intra-process-comms", name=f"fleet_{host}", cwd=REPO,
                          log_path=session.parent / f"{host}.log"):
        client = ContainerClient(probe, f"/fleet_{host}")
        try:
            client.wait()
            custom = [f"{key}={value}" for key, value in fleet(host).items() if value]
            recorder = client.load("components::Recorder", name=f"recorder_{host}", parameters={
                "record.topics": [f"/{host}/chatter"], "storage.uri": str(bag), "storage.custom_data": custom})
            assert recorder.success, recorder.error_message
            talker = client.load("components::Talker", namespace=f"/{host}", parameters={"rate": 100.0})
            assert talker.success, talker.error_message
            assert wait_until(lambda: len(heard) >= count, 30.0, probe), f"{len(heard)} of {count} heard"
            assert client.unload(recorder.unique_id).success
        finally:
            client.destroy()
            probe.destroy_subscription(subscription)
    return bag


def test_merges_what_the_recorder_recorded_on_two_computers(probe: Node, tmp_path: Path) -> None:
    session = tmp_path / "session"
    bags = [record_fleet_bag(probe, session, host, 40) for host in ("alpha", "beta")]
    inputs = [rosbags_messages(bag) for bag in bags]
    assert all(len(messages) >= 20 for messages in inputs), [len(messages) for messages in inputs]
    done = merge(tmp_path / "merged", *bags, "--align-clocks")
    assert done.returncode == 0, done.stderr
    expected = sorted((message for messages in inputs for message in messages), key=lambda message: message[1])
    assert rosbags_messages(tmp_path / "merged") == expected
    assert mcap_messages(tmp_path / "merged") == expected
    custom = metadata(tmp_path / "merged")["custom_data"]
    assert custom["input.1.ipc.host"] == "beta" and custom["input.0.ipc.session"] == "s1"


def test_custom_data_of_every_input_is_kept(tmp_path: Path) -> None:
    bags, _ = four_inputs(tmp_path)
    assert merge(tmp_path / "merged", *bags).returncode == 0
    custom = metadata(tmp_path / "merged")["custom_data"]
    assert {custom[fleet_keys.input_key(index, "path")] for index in range(4)} == {str(bag) for bag in bags}
    assert {key.removeprefix("input.3."): value for key, value in custom.items()
            if key.startswith("input.3.") and key != "input.3.path"} == fleet("cam-host.local")


def test_prefix_host_keeps_the_inputs_topics_apart(tmp_path: Path) -> None:
    plans = [plan_of(index, "/count") for index in range(3)]
    bags = [rosbag2_layout(tmp_path / "robot_a", plans[0]),
            recorder_bag(tmp_path / "b", plans[1], fleet("cam-host.local")),
            recorder_bag(tmp_path / "c", plans[2], fleet("10.0.0.7"))]
    # b and c were recorded by different containers: one topic of both only when asked for
    refused = merge(tmp_path / "refused", *bags)
    assert refused.returncode == 1 and "/chatter (from 10.0.0.7 main, cam-host.local main)" in refused.stderr
    assert "/count" in refused.stderr and "--prefix-container" in refused.stderr and not (tmp_path / "refused").exists()
    assert merge(tmp_path / "together", *bags, "--interleave", "/c*").returncode == 0
    assert sorted({topic for topic, _, _ in rosbags_messages(tmp_path / "together")}) == ["/chatter", "/count"]
    done = merge(tmp_path / "apart", *bags, "--prefix-host")
    assert done.returncode == 0, done.stderr
    prefixes = ["/robot_a", "/cam_host_local", "/_10_0_0_7"]  # the directory's name when there is no ipc.host
    assert rosbags_messages(tmp_path / "apart") == merged_order(plans, lambda index, topic: prefixes[index] + topic)


def test_two_containers_on_one_computer_are_kept_apart_by_container(tmp_path: Path) -> None:
    """Two rigs on one computer (containers /front/container and /rear/container) with drivers named alike: their
    topics are never interleaved silently; --prefix-host cannot part them (one host), --prefix-container does."""
    plans = [plan_of(index, "/front_camera/image_raw") for index in range(2)]
    bags = [recorder_bag(tmp_path / rig, plan, {**fleet("bench-pc"), fleet_keys.CONTAINER: f"/{rig}/container"})
            for rig, plan in zip(("front", "rear"), plans)]
    for options in ((), ("--prefix-host",)):
        refused = merge(tmp_path / "refused", *bags, *options)
        assert refused.returncode == 1 and not (tmp_path / "refused").exists(), refused.stderr
        prefix = "/bench_pc" if options else ""
        for topic in ("/chatter", "/front_camera/image_raw"):
            assert (f"{prefix}{topic} (from bench-pc /front/container, bench-pc /rear/container)"
                    in refused.stderr), refused.stderr
        assert "--prefix-container" in refused.stderr and "--interleave" in refused.stderr
    done = merge(tmp_path / "apart", *bags, "--prefix-container")
    assert done.returncode == 0, done.stderr
    prefixes = ["/front/container", "/rear/container"]
    assert rosbags_messages(tmp_path / "apart") == merged_order(plans, lambda index, topic: prefixes[index] + topic)
    done = merge(tmp_path / "both", *bags, "--prefix-container", "--prefix-host")
    assert done.returncode == 0, done.stderr
    assert {topic for topic, _, _ in rosbags_messages(tmp_path / "both")} == {
        f"/bench_pc{prefix}{topic}" for prefix in prefixes for topic in ("/chatter", "/front_camera/image_raw")}


def test_bags_of_one_container_and_bags_that_do_not_say_merge_by_name(tmp_path: Path) -> None:
    """A container's bags of two sessions are one rig; a bag without fleet keys names no container."""
    plans = [plan_of(index, "/count") for index in range(3)]
    bags = [recorder_bag(tmp_path / "monday", plans[0], fleet("bench-pc")),
            recorder_bag(tmp_path / "tuesday", plans[1], fleet("bench-pc")),
            rosbags_bag(tmp_path / "plain", plans[2], "MCAP")]
    done = merge(tmp_path / "merged", *bags)
    assert done.returncode == 0, done.stderr
    assert rosbags_messages(tmp_path / "merged") == merged_order(plans)


def test_align_clocks_moves_each_input_by_its_offset(tmp_path: Path) -> None:
    plans = [plan_of(index, f"/count{index}") for index in range(2)]
    offsets = [0, 3 * MS + 500]  # input 1's clock runs 3.0005 ms ahead of the commanding host's
    bags = [recorder_bag(tmp_path / f"in{index}", plan, fleet(f"host{index}", offsets[index]))
            for index, plan in enumerate(plans)]
    done = merge(tmp_path / "aligned", *bags, "--align-clocks", "--interleave", "/chatter")
    assert done.returncode == 0, done.stderr
    shifted = [[(topic, t - offsets[index], data) for topic, t, data in plan] for index, plan in enumerate(plans)]
    assert mcap_messages(tmp_path / "aligned") == merged_order(shifted)
    custom = metadata(tmp_path / "aligned")["custom_data"]
    assert custom["input.1.shift_ns"] == str(offsets[1])
    # a bag without a recorded offset cannot be aligned: refused, nothing written
    plain = rosbags_bag(tmp_path / "plain", plan_of(2, "/count2"), "MCAP")
    done = merge(tmp_path / "refused", bags[0], plain, "--align-clocks")
    assert done.returncode == 1 and fleet_keys.CLOCK_OFFSET_NS in done.stderr and str(plain) in done.stderr
    assert not (tmp_path / "refused").exists()


def test_a_topic_with_two_types_is_refused_naming_both_inputs(tmp_path: Path) -> None:
    first = recorder_bag(tmp_path / "first", plan_of(0, "/value"))
    with BagWriter(tmp_path / "second") as writer:  # /value is a String here, an Int32 in the first
        writer.add_topic(TopicInfo("/value", STRING))
        writer.write("/value", chatter("x"), T0, T0)
    done = merge(tmp_path / "merged", first, tmp_path / "second")
    assert done.returncode == 1
    assert "/value" in done.stderr and str(first) in done.stderr and str(tmp_path / "second") in done.stderr
    assert not (tmp_path / "merged").exists()
    done = merge(tmp_path / "apart", first, tmp_path / "second", "--prefix-host")  # apart, they may differ
    assert done.returncode == 0, done.stderr


def cut_mcap(bag: Path) -> None:
    """The last file loses its end, as a recorder killed mid-write leaves it (metadata.yaml still lists it)."""
    last = sorted(bag.glob("*.mcap"))[-1]
    last.write_bytes(last.read_bytes()[:-100])


def unlisted_file(bag: Path) -> None:
    """A split file the crash kept out of metadata.yaml."""
    shutil.copy(sorted(bag.glob("*.mcap"))[0], bag / f"{bag.name}_99.mcap")


def no_metadata(bag: Path) -> None:
    (bag / "metadata.yaml").unlink()


def sqlite_journal(bag: Path) -> None:
    """An SQLite3 database a crash left with its rollback journal."""
    first = sorted(bag.glob("*.db3"))[0]
    first.with_name(first.name + "-journal").write_bytes(b"\0" * 512)


@pytest.mark.parametrize("crash", [cut_mcap, unlisted_file, no_metadata, sqlite_journal])
def test_a_crashed_input_is_refused_with_the_recover_hint(tmp_path: Path, crash: Any) -> None:
    good = recorder_bag(tmp_path / "good", plan_of(0, "/count0"))
    storage_id = "sqlite3" if crash is sqlite_journal else "mcap"
    crashed = recorder_bag(tmp_path / "crashed", plan_of(1, "/count1"), storage_id=storage_id)
    crash(crashed)
    done = merge(tmp_path / "merged", good, crashed)
    assert done.returncode == 1
    assert f"ipc-component bag recover {crashed}" in done.stderr and done.stdout == ""
    assert not (tmp_path / "merged").exists()


def test_an_existing_output_is_refused(tmp_path: Path) -> None:
    bag = recorder_bag(tmp_path / "in", plan_of(0, "/count0"))
    (tmp_path / "out").mkdir()
    done = merge(tmp_path / "out", bag)
    assert done.returncode == 1 and "already exists" in done.stderr
    assert list((tmp_path / "out").iterdir()) == []


def peak_rss_of_merge(inputs: list[Path], output: Path) -> int:
    """Peak RSS (KiB) of a fresh process that merges ``inputs`` into ``output``."""
    code = ("import resource, sys; from baglib.tools.merge import merge_bags; "
            "merge_bags(sys.argv[1], sys.argv[2:]); print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    done = subprocess.run([sys.executable, "-c", code, str(output), *map(str, inputs)], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return int(done.stdout)


def frames_bag(path: Path, index: int, megabytes: int) -> Path:
    """``megabytes`` of 256 KiB frames, interleaved in time with the other inputs'."""
    frame = bytearray(os.urandom(256 * 1024))
    with BagWriter(path) as writer:
        writer.add_topic(TopicInfo("/frames", "sensor_msgs/msg/Image"))
        for n in range(megabytes * 4):
            frame[:8] = n.to_bytes(8, "little")
            t = T0 + n * 10 * MS + index
            writer.write("/frames", bytes(frame), t, t)
    return path


def test_memory_does_not_grow_with_the_inputs(tmp_path: Path) -> None:
    small = [frames_bag(tmp_path / f"small{index}", index, 30) for index in range(2)]
    large = [frames_bag(tmp_path / f"large{index}", index, 150) for index in range(2)]
    small_rss = peak_rss_of_merge(small, tmp_path / "small_out")
    large_rss = peak_rss_of_merge(large, tmp_path / "large_out")
    # the inputs grew by 240 MB; a merge that held messages would grow with them
    assert large_rss - small_rss < 40 * 1024, (small_rss, large_rss)
    assert sum(f.stat().st_size for f in (tmp_path / "large_out").glob("*.mcap")) > 290e6


def mount_namespace_available() -> bool:
    return os.geteuid() == 0 and shutil.which("unshare") is not None and subprocess.run(
        ["unshare", "-m", "true"], capture_output=True).returncode == 0


def in_mount_namespace(setup: str, *command: str | Path) -> subprocess.CompletedProcess:
    """``command`` in a private mount namespace prepared by the shell commands ``setup`` (its mounts vanish with
    it: nothing to unmount, nothing seen outside)."""
    script = f'{setup} && exec "$@"'
    return subprocess.run(["unshare", "-m", "sh", "-c", script, "sh", *map(str, command)], capture_output=True,
                          text=True, timeout=120)


@pytest.mark.skipif(not mount_namespace_available(), reason="needs root and unshare -m for a bind mount")
def test_merges_from_a_read_only_bind_mount(tmp_path: Path) -> None:
    source, mounted = tmp_path / "session", tmp_path / "read_only"
    source.mkdir()
    mounted.mkdir()
    bags, plans = four_inputs(source)
    before = tree_digest(source)
    done = in_mount_namespace(f"mount --bind {source} {mounted} && mount -o remount,bind,ro {mounted}",
                              CLI, "bag", "merge", tmp_path / "merged", *(mounted / bag.name for bag in bags))
    assert done.returncode == 0, done.stderr
    assert rosbags_messages(tmp_path / "merged") == merged_order(plans)
    assert tree_digest(source) == before  # not a byte, not a timestamp changed


@pytest.mark.skipif(not mount_namespace_available(), reason="needs root and unshare -m for a small tmpfs")
def test_a_full_disk_leaves_no_half_merged_bag(tmp_path: Path) -> None:
    bags = [frames_bag(tmp_path / f"in{index}", index, 4) for index in range(2)]
    disk = tmp_path / "disk"
    disk.mkdir()
    done = in_mount_namespace(f"mount -t tmpfs -o size=3m tmpfs {disk}",
                              "sh", "-c", '"$@"; status=$?; ls -A "$0"; exit $status', disk,
                              CLI, "bag", "merge", disk / "merged", *bags)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "nothing kept" in done.stderr and "No space left" in done.stderr
    assert done.stdout == ""  # the listing of the tmpfs after the merge: empty


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_type_not_installed_here_is_copied_with_its_recorded_definition(tmp_path: Path, storage: str) -> None:
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg("int32 x\nstring note", "not_installed_msgs/msg/Thing"))
    things = [store.serialize_cdr(store.types["not_installed_msgs/msg/Thing"](x=n, note=f"n{n}"),
                                  "not_installed_msgs/msg/Thing") for n in range(5)]
    with Writer(tmp_path / "things", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/thing", "not_installed_msgs/msg/Thing", typestore=store)
        for n, data in enumerate(things):
            writer.write(connection, T0 + n * MS, data)
    other = recorder_bag(tmp_path / "other", plan_of(0, "/count0"))
    done = merge(tmp_path / "merged", tmp_path / "things", other, "-s", storage)
    assert done.returncode == 0, done.stderr
    with AnyReader([tmp_path / "merged"]) as reader:  # types from the bag's own definitions
        decoded = [reader.deserialize(data, connection.msgtype) for connection, _, data in reader.messages()
                   if connection.topic == "/thing"]
    assert [(thing.x, thing.note) for thing in decoded] == [(n, f"n{n}") for n in range(5)]


LOG = "rcl_interfaces/msg/Log"
#: A version of rcl_interfaces/msg/Log other than the installed one (its ``line`` an int32): its hash differs.
OTHER_LOG = ("ros2msg", message_definition(LOG)[1].replace("uint32 line", "int32 line"))


def older_talker_bag(path: Path, index: int) -> Path:
    """A talker's bag as a rosbag2 before Iron wrote it (MCAP, metadata version 5): no type hashes anywhere, and
    the definitions of the type versions it had (here a /rosout Log that is not the installed version)."""
    topics = [LegacyTopic("/chatter", STRING, definition=message_definition(STRING)),
              LegacyTopic("/rosout", LOG, definition=OTHER_LOG)]
    messages = [message for n in range(10) for message in (
        ("/chatter", T0 + n * MS + index, T0 + n * MS + index, chatter(f"talker {index} says {n}")),
        ("/rosout", T0 + n * MS + index, T0 + n * MS + index,
         bytes(serialize(Log(level=20, name=f"talker{index}", msg=f"Publishing {n}", line=n)))))]
    path.mkdir()
    write_mcap(path / f"{path.name}_0.mcap", topics, messages, 5, type_hashes=False)
    write_metadata(path, metadata_document(5, "mcap", [f"{path.name}_0.mcap"], topics, [messages]))
    return path


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_type_hashes_agree_with_the_definitions_the_merged_bag_carries(tmp_path: Path, storage: str) -> None:
    """The hash of each topic is the one of the definition written: the input's (none from an older rosbag2) or,
    for the installed definition, the installed type's. rosbags checks them and opens the bag."""
    talkers = [older_talker_bag(tmp_path / f"talker{index}", index) for index in range(2)]
    done = merge(tmp_path / "merged", *talkers, "-s", storage)
    assert done.returncode == 0, done.stderr
    hashes = {entry["topic_metadata"]["name"]: entry["topic_metadata"]["type_description_hash"]
              for entry in metadata(tmp_path / "merged")["topics_with_message_count"]}
    assert hashes == {"/chatter": type_hash(STRING), "/rosout": ""}
    with AnyReader([tmp_path / "merged"]) as reader:
        logs = [reader.deserialize(data, connection.msgtype) for connection, _, data in reader.messages()
                if connection.topic == "/rosout"]
    assert sorted((log.name, log.line) for log in logs) == [(f"talker{i}", n) for i in range(2) for n in range(10)]
    # A Jazzy bag of the same type (installed definition and hash) merged after them: the older definition
    # describes the type, so its topics carry that definition's hash (none), not the Jazzy one.
    with BagWriter(tmp_path / "jazzy") as writer:
        writer.add_topic(TopicInfo("/rosout", LOG))
        writer.write("/rosout", bytes(serialize(Log(level=30, name="jazzy", msg="hi", line=7))), T0 + 50 * MS,
                     T0 + 50 * MS)
    done = merge(tmp_path / "mixed", *talkers, tmp_path / "jazzy", "-s", storage)
    assert done.returncode == 0, done.stderr
    with AnyReader([tmp_path / "mixed"]) as reader:
        names = {reader.deserialize(data, connection.msgtype).name for connection, _, data in reader.messages()
                 if connection.topic == "/rosout"}
    assert names == {"talker0", "talker1", "jazzy"}


def test_a_type_nobody_describes_is_refused(tmp_path: Path) -> None:
    """A Humble-era SQLite3 bag keeps no message definitions; a type not installed here cannot be described."""
    topics = [LegacyTopic("/thing", "not_installed_msgs/msg/Thing")]
    messages = [("/thing", T0, T0, b"\0\1\0\0\7\0\0\0")]
    bag = tmp_path / "humble"
    bag.mkdir()
    write_sqlite(bag / "humble_0.db3", 3, topics, messages, 5)
    write_metadata(bag, metadata_document(5, "sqlite3", ["humble_0.db3"], topics, [messages]))
    done = merge(tmp_path / "merged", bag)
    assert done.returncode == 1 and "not_installed_msgs/msg/Thing" in done.stderr, done.stderr
    assert not (tmp_path / "merged").exists()
