"""``components::Player`` as users run it: a real container process, real Fast DDS, bags on disk.

Every test writes its bag with this project's BagWriter (or rosbags, for what BagWriter refuses to write),
loads a player into a container started with intra-process comms next to a ``PlaybackProbe`` (an in-process
subscriber that reports receive times and the CDR digest of each message), and checks what arrived: every
message, byte for byte, in bag order, on schedule; the rosbag2 services against their Jazzy behaviour; an
out-of-process subscriber gets the recorded bytes over DDS.
"""
from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Any

import pytest
from builtin_interfaces.msg import Duration as DurationMsg
from builtin_interfaces.msg import Time as TimeMsg
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbag2_interfaces.msg import ReadSplitEvent
from rosbag2_interfaces.srv import (
    Burst,
    GetRate,
    IsPaused,
    Pause,
    Play,
    PlayNext,
    Resume,
    Seek,
    SetRate,
    Stop,
    TogglePaused,
)
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from sensor_msgs.msg import Image
from std_msgs.msg import String
from service_msgs.msg import ServiceEventInfo
from std_srvs.srv import SetBool, Trigger

from baglib.format.cdr_fast import serialize
from baglib.format.metadata import TopicInfo, qos_profile_dict
from baglib.write.writer import BagWriter
from container_process import ContainerClient, call, wait_until

IPC = {"use_intra_process_comms": True}
PLAYER = "components::Player"
PROBE = "tests.container_test_plugins:PlaybackProbe"
RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
T0 = 1_700_000_000_000_000_000
MS = 1_000_000


# --- bags ----------------------------------------------------------------------------------------------------
def wire(msg: Any) -> bytes:
    """The exact CDR of ``msg`` (rclpy's serialize_message pads with uninitialized bytes)."""
    return bytes(serialize(msg))


def chatter(n: int) -> bytes:
    return wire(String(data=f"message {n}"))


def image(n: int, height: int = 24) -> bytes:
    """A 32-pixel wide rgb8 image whose bytes depend on ``n``."""
    msg = Image(height=height, width=32, encoding="rgb8", step=96,
                data=bytes((n + i) % 256 for i in range(height * 96)))
    msg.header.frame_id = f"frame {n}"
    return wire(msg)


def write_bag(path: Path, plan: list[tuple[str, int, bytes]], storage_id: str = "mcap", **options: Any) -> Path:
    """``plan``: (topic, offset from T0 in ns, CDR) in write order; /chatter is String, /image Image."""
    types = {"/chatter": "std_msgs/msg/String", "/image": "sensor_msgs/msg/Image"}
    with BagWriter(path, storage_id=storage_id, **options) as writer:
        for topic in sorted({topic for topic, _, _ in plan}):
            writer.add_topic(TopicInfo(topic, types[topic], offered_qos_profiles=[qos_profile_dict(RELIABLE)]))
        for topic, offset, data in plan:
            writer.write(topic, data, T0 + offset, T0 + offset)
    return path


def regular_plan(count: int, period_ms: int = 20, height: int = 24) -> list[tuple[str, int, bytes]]:
    """``count`` chatter messages ``period_ms`` apart, an image every third one."""
    plan = []
    for n in range(count):
        plan.append(("/chatter", n * period_ms * MS, chatter(n)))
        if n % 3 == 0:
            plan.append(("/image", n * period_ms * MS, image(n, height)))
    return plan


def assert_spacing(times: list[int], nominal_ms: float, behind: dict[str, float] | None = None) -> None:
    """Receive times follow the schedule: the median gap is the nominal one and the whole span is the
    nominal one (receive times include the subscriber's executor latency, which a loaded 2-core CI machine
    stretches for single messages; punctuality itself is the benchmark's measure).

    ``behind`` is the player's own report of falling behind (``get_stats``): each time a stall of the machine
    made it more than 10 ms late it moved the schedule back by that lateness, by design. Those moves must
    account for the extra span, and each stretches at most one gap (left out of the median)."""
    count, shifted_ms = (int(behind["count"]), behind["total_s"] * 1000) if behind else (0, 0.0)
    gaps = sorted((b - a) / MS for a, b in zip(times, times[1:]))
    kept = gaps[:len(gaps) - count] or gaps
    assert abs(kept[len(kept) // 2] - nominal_ms) < 0.2 * nominal_ms, (gaps, behind)
    span = (times[-1] - times[0]) / MS
    assert abs(span - shifted_ms - nominal_ms * len(gaps)) < 0.1 * nominal_ms * len(gaps) + 50, (span, gaps, behind)


def digest(data: bytes) -> str:
    return hashlib.sha1(data).hexdigest()


# --- the player through its services ------------------------------------------------------------------------
class PlayerHandle:
    """A loaded player and a probe next to it, driven from the test's node; unloaded at the end of ``with``.

    Each handle's nodes get names of their own, so a test never talks to another test's player."""

    created = 0
    live: list[PlayerHandle] = []

    def __init__(self, node: Node, client: ContainerClient, bag: Path, parameters: dict[str, Any] | None = None,
                 topics: tuple[tuple[str, str], ...] = (("/chatter", "std_msgs/msg/String"),
                                                        ("/image", "sensor_msgs/msg/Image"))) -> None:
        PlayerHandle.created += 1
        self.node = node
        self.client = client
        self.name = name = f"player{PlayerHandle.created}"
        self.unique_id = self.probe_id = 0
        PlayerHandle.live.append(self)
        probe = client.load(PROBE, "tests", name=f"{name}_probe", extra=IPC,
                            parameters={"topics": [t for t, _ in topics] or [""],  # [] would be a byte array
                                        "types": [t for _, t in topics] or [""]})
        assert probe.success, probe.error_message
        self.probe_id = probe.unique_id
        loaded = client.load(PLAYER, name=name, extra=IPC,
                             parameters={"storage.uri": str(bag), **(parameters or {})})
        assert loaded.success, loaded.error_message
        self.unique_id = loaded.unique_id

    def call(self, srv_type: Any, service: str, request: Any = None, timeout: float = 10.0) -> Any:
        client = self.node.create_client(srv_type, service)
        try:
            assert client.wait_for_service(timeout_sec=timeout), f"{service} not available"
            return call(self.node, client, request or srv_type.Request(), timeout, again=True)
        finally:
            self.node.destroy_client(client)

    def player(self, srv_type: Any, service: str, request: Any = None) -> Any:
        return self.call(srv_type, f"/{self.name}/{service}", request)

    def stats(self) -> dict[str, Any]:
        return json.loads(self.player(Trigger, "get_stats").message)

    def report(self) -> dict[str, Any]:
        return json.loads(self.call(Trigger, f"/{self.name}_probe/report").message)

    def wait_finished(self, timeout: float = 20.0) -> dict[str, Any]:
        stats = wait_until(lambda: (s := self.stats()) and not s["playing"] and s, timeout)
        assert stats, f"playback did not finish within {timeout} s: {self.stats()}"
        return stats

    def unload(self) -> None:
        for unique_id in (self.unique_id, self.probe_id):
            if unique_id:
                assert self.client.unload(unique_id).success
        self.unique_id = self.probe_id = 0


@pytest.fixture(autouse=True)
def unload_players() -> Any:
    """Whatever a test left loaded (it failed half-way) is unloaded before the next test starts."""
    yield
    while PlayerHandle.live:
        PlayerHandle.live.pop().unload()


@pytest.fixture(scope="module")
def container(ros: None, tmp_path_factory: pytest.TempPathFactory) -> Any:
    from container_process import Containers

    node = Node("player_test")
    started = Containers(node)
    try:
        process, client = started.start("--use-intra-process-comms", "--allow-module-plugins", "--low-latency")
        yield node, client, process
    finally:
        started.close()
        node.destroy_node()


def received(report: dict[str, Any], topic: str) -> list[str]:
    return report[topic]["digests"]


def expected(plan: list[tuple[str, int, bytes]], topic: str) -> list[str]:
    return [digest(data) for t, _, data in sorted(plan, key=lambda p: p[1]) if t == topic]


# --- tests ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("storage_id", ["mcap", "sqlite3"])
def test_plays_every_message_in_order_on_schedule(container: Any, tmp_path: Path, storage_id: str) -> None:
    node, client, process = container
    plan = regular_plan(60)
    bag = write_bag(tmp_path / "bag", plan, storage_id)
    handle = PlayerHandle(node, client, bag)
    stats = handle.wait_finished()
    report = handle.report()
    for topic in ("/chatter", "/image"):
        assert received(report, topic) == expected(plan, topic)
    assert stats["published"] == {"/chatter": 60, "/image": 20}
    # Receive-time offsets follow the bag's (20 ms apart) within a few ms; the player's own error is tighter.
    assert_spacing(report["/chatter"]["times"], 20, stats["behind"])
    assert stats["publish_error_ms"]["count"] == 80
    handle.unload()


def test_out_of_process_subscriber_gets_the_recorded_bytes(container: Any, tmp_path: Path) -> None:
    node, client, process = container
    plan = regular_plan(30)
    bag = write_bag(tmp_path / "bag", plan)
    got: list[bytes] = []
    subscription = node.create_subscription(String, "/chatter", got.append, RELIABLE, raw=True)
    try:
        handle = PlayerHandle(node, client, bag, {"play.delay.sec": 2})  # time to match the reader
        assert wait_until(lambda: len(got) >= 30, 20.0, node), f"{len(got)} of 30"
        # As recorded, but for the zero padding Fast DDS appends to a raw sample to reach a multiple of 4
        # bytes (rosbag2's player goes through the same rmw call, so its samples get the same padding).
        recorded = [data for topic, _, data in plan if topic == "/chatter"]
        assert got == [data + bytes(-len(data) % 4) for data in recorded]
        handle.unload()
    finally:
        node.destroy_subscription(subscription)


def test_equal_timestamps_keep_file_order(container: Any, tmp_path: Path) -> None:
    node, client, process = container
    plan = [("/chatter", (n // 5) * 10 * MS, chatter(n)) for n in range(50)]  # groups of five equal times
    bag = write_bag(tmp_path / "bag", plan)
    handle = PlayerHandle(node, client, bag, topics=(("/chatter", "std_msgs/msg/String"),))
    handle.wait_finished()
    assert received(handle.report(), "/chatter") == [digest(data) for _, _, data in plan]
    handle.unload()


def test_unknown_type_is_skipped_and_the_rest_plays(container: Any, tmp_path: Path) -> None:
    node, client, process = container
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg("int32 x", "not_installed_msgs/msg/Thing"))
    bag = tmp_path / "bag"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        thing = writer.add_connection("/thing", "not_installed_msgs/msg/Thing", typestore=store)
        text = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        for n in range(10):
            writer.write(thing, T0 + n * 10 * MS, store.serialize_cdr(
                store.types["not_installed_msgs/msg/Thing"](x=n), "not_installed_msgs/msg/Thing"))
            writer.write(text, T0 + n * 10 * MS, chatter(n))
    handle = PlayerHandle(node, client, bag, topics=(("/chatter", "std_msgs/msg/String"),))
    stats = handle.wait_finished()
    assert stats["published"] == {"/chatter": 10}
    assert received(handle.report(), "/chatter") == [digest(chatter(n)) for n in range(10)]
    handle.unload()
    warning = [line for line in process.output.splitlines() if "/thing" in line]
    assert warning and "not_installed_msgs/msg/Thing" in warning[0], process.output

def test_services_follow_rosbag2(container: Any, tmp_path: Path) -> None:
    """pause / is_paused / play_next / burst / resume / toggle / rates / seek / stop / play, as in Jazzy."""
    node, client, process = container
    plan = [("/chatter", n * 100 * MS, chatter(n)) for n in range(50)]  # 5 s of bag
    bag = write_bag(tmp_path / "bag", plan)
    handle = PlayerHandle(node, client, bag, {"play.start_paused": True},
                          topics=(("/chatter", "std_msgs/msg/String"),))
    all_digests = expected(plan, "/chatter")
    assert handle.player(IsPaused, "is_paused").paused
    time.sleep(0.5)
    assert received(handle.report(), "/chatter") == []
    # play_next publishes exactly one message, in order, only while paused
    assert handle.player(PlayNext, "play_next").success
    assert handle.player(PlayNext, "play_next").success
    assert wait_until(lambda: received(handle.report(), "/chatter") == all_digests[:2], 5.0)
    # burst: exactly N more
    assert handle.player(Burst, "burst", Burst.Request(num_messages=3)).actually_burst == 3
    assert wait_until(lambda: received(handle.report(), "/chatter") == all_digests[:5], 5.0)
    # rates: invalid ones are refused and change nothing
    assert not handle.player(SetRate, "set_rate", SetRate.Request(rate=0.0)).success
    assert not handle.player(SetRate, "set_rate", SetRate.Request(rate=-1.0)).success
    assert handle.player(SetRate, "set_rate", SetRate.Request(rate=4.0)).success
    assert handle.player(GetRate, "get_rate").rate == 4.0
    # seek back to the start while paused, then resume: the bag plays from there, each message once
    assert handle.player(Seek, "seek", Seek.Request(time=TimeMsg(sec=0, nanosec=0))).success  # clamped
    handle.player(TogglePaused, "toggle_paused")
    assert not handle.player(IsPaused, "is_paused").paused
    # play while playing is refused
    assert not handle.player(Play, "play").success
    stats = handle.wait_finished(20.0)
    assert received(handle.report(), "/chatter") == all_digests[:5] + all_digests
    assert stats["publish_error_ms"]["count"] == 50  # the resumed run: every message through the schedule
    # play_next after the end: nothing left, not paused -> False
    assert not handle.player(PlayNext, "play_next").success
    # play again with a start offset and a duration: 1.0 s .. 2.0 s of the bag
    request = Play.Request(start_offset=TimeMsg(sec=1), playback_duration=DurationMsg(sec=1),
                           playback_until_timestamp=TimeMsg(sec=0, nanosec=0))
    assert handle.player(Play, "play", request).success
    handle.wait_finished()
    assert received(handle.report(), "/chatter")[55:] == all_digests[10:21]
    handle.unload()


def test_pause_and_rate_keep_the_schedule(container: Any, tmp_path: Path) -> None:
    """A pause holds bag time (no catch-up burst after resume); rate 2 halves the gaps."""
    node, client, process = container
    plan = [("/chatter", n * 50 * MS, chatter(n)) for n in range(60)]  # 3 s of bag, 50 ms apart
    bag = write_bag(tmp_path / "bag", plan)
    handle = PlayerHandle(node, client, bag, topics=(("/chatter", "std_msgs/msg/String"),))
    time.sleep(0.6)
    handle.player(Pause, "pause")
    time.sleep(1.0)
    handle.player(SetRate, "set_rate", SetRate.Request(rate=2.0))
    handle.player(Resume, "resume")
    handle.wait_finished()
    report = handle.report()
    assert received(report, "/chatter") == expected(plan, "/chatter")
    times = report["/chatter"]["times"]
    gaps = [(b - a) / MS for a, b in zip(times, times[1:])]
    pause = max(range(len(gaps)), key=gaps.__getitem__)
    assert gaps[pause] > 900, gaps  # the pause itself
    assert_spacing(times[:pause + 1], 50)
    assert_spacing(times[pause + 1:], 25)  # rate 2
    resumed = times[pause + 1]
    assert sum(resumed <= t < resumed + 100 * MS for t in times) <= 6  # no catch-up burst: 4 in 100 ms
    handle.unload()


def test_stop_ends_playback_and_unload_mid_playback_is_clean(container: Any, tmp_path: Path) -> None:
    node, client, process = container
    plan = [("/chatter", n * 100 * MS, chatter(n)) for n in range(100)]  # 10 s
    bag = write_bag(tmp_path / "bag", plan)
    handle = PlayerHandle(node, client, bag, topics=(("/chatter", "std_msgs/msg/String"),))
    time.sleep(0.5)
    handle.player(Stop, "stop")
    stats = handle.stats()
    assert not stats["playing"]
    count = len(received(handle.report(), "/chatter"))
    time.sleep(0.5)
    assert len(received(handle.report(), "/chatter")) == count < 100
    assert handle.player(Play, "play").success  # a new run from the start
    time.sleep(0.5)
    handle.unload()  # mid-playback
    assert all(name != "/player" for name in client.list().full_node_names)


def test_loop_filters_and_split_events(container: Any, tmp_path: Path) -> None:
    node, client, process = container
    plan = regular_plan(30, height=200)  # 10 images of 19 KB
    bag = write_bag(tmp_path / "bag", plan, max_bagfile_size=86016)  # several files
    files = sorted(p.name for p in bag.glob("*.mcap"))
    assert len(files) >= 2
    events: list[ReadSplitEvent] = []
    name = f"player{PlayerHandle.created + 1}"  # the next handle's player
    # rosbag2's relative "events/read_split": in the node's namespace, here "/"
    subscription = node.create_subscription(ReadSplitEvent, "/events/read_split", events.append, 10)
    try:
        handle = PlayerHandle(node, client, bag, {"play.topics_to_filter": ["/image"], "play.loop": True,
                                                  "play.delay.nsec": 500_000_000})
        images = expected(plan, "/image")
        assert wait_until(lambda: len(received(handle.report(), "/image")) >= 2 * len(images) + 1, 20.0)
        assert received(handle.report(), "/image")[: 2 * len(images)] == images * 2
        assert received(handle.report(), "/chatter") == []
        wait_until(lambda: len(events) >= len(files) - 1, 5.0, node)
        assert [Path(e.opened_file).name for e in events[: len(files) - 1]] == files[1:]
        assert all(e.node_name == f"/{name}" for e in events)
        handle.unload()
    finally:
        node.destroy_subscription(subscription)


def test_a_truncated_bag_plays_what_is_intact(container: Any, tmp_path: Path) -> None:
    """A file cut short (a crash while recording, metadata.yaml from the last split) plays up to the damage:
    a prefix of the messages, in order; the container stays up."""
    node, client, process = container
    plan = [("/chatter", n * 10 * MS, chatter(n)) for n in range(200)]
    bag = write_bag(tmp_path / "bag", plan, storage_preset_profile="fastwrite")  # one record per message
    (file,) = bag.glob("*.mcap")
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])
    handle = PlayerHandle(node, client, bag, topics=(("/chatter", "std_msgs/msg/String"),))
    handle.wait_finished()
    got = received(handle.report(), "/chatter")
    assert 50 < len(got) < 200
    assert got == expected(plan, "/chatter")[: len(got)]
    handle.unload()
    assert process.alive()


# --- bags of other writers ----------------------------------------------------------------------------------
def chatter_messages(count: int) -> list[tuple[str, int, int, bytes]]:
    return [("/chatter", T0 + n * 20 * MS, T0 + n * 20 * MS, chatter(n)) for n in range(count)]


def rosbags_bag(path: Path, storage: str, compression: str) -> Path:
    """Written by rosbags' own writer (MCAP or SQLite3; rosbag2's FILE or MESSAGE zstd compression)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    writer = Writer(path, version=9, storage_plugin=StoragePlugin[storage])
    if compression:
        writer.set_compression(CompressionMode[compression], CompressionFormat.ZSTD)
    with writer:
        connection = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        for _, log_time, _, data in chatter_messages(30):
            writer.write(connection, log_time, data)
    return path


def legacy_bag(path: Path, layout: str) -> Path:
    """rosbag2 layouts of older releases, written from rosbag2's sources (tests/legacy_bags.py)."""
    from legacy_bags import LegacyTopic, metadata_document, write_metadata, write_mcap, write_sqlite
    from mcap.writer import CompressionType

    topics = [LegacyTopic("/chatter", "std_msgs/msg/String", [qos_profile_dict(RELIABLE)])]
    messages = chatter_messages(30)
    path.mkdir()
    if layout == "foxy-sqlite3-message-compressed":  # metadata v4, schema 2, each message zstd
        files, parts = ["bag_0.db3", "bag_1.db3"], [messages[:15], messages[15:]]
        for name, part in zip(files, parts):
            write_sqlite(path / name, 2, topics, part, 4, compress_messages=True)
        write_metadata(path, metadata_document(4, "sqlite3", files, topics, parts, compression_mode="MESSAGE",
                                               compression_format="zstd"))
    elif layout == "humble-sqlite3":  # metadata v5, schema 3
        write_sqlite(path / "bag_0.db3", 3, topics, messages, 5, ros_distro="humble")
        write_metadata(path, metadata_document(5, "sqlite3", ["bag_0.db3"], topics, [messages]))
    else:  # "iron-mcap-lz4": metadata v8, lz4 chunks
        write_mcap(path / "bag_0.mcap", topics, messages, 8, compression=CompressionType.LZ4)
        write_metadata(path, metadata_document(8, "mcap", ["bag_0.mcap"], topics, [messages], ros_distro="iron"))
    return path


@pytest.mark.parametrize("writer", ["rosbags-MCAP", "rosbags-SQLITE3", "rosbags-MCAP-FILE",
                                    "rosbags-SQLITE3-MESSAGE", "foxy-sqlite3-message-compressed",
                                    "humble-sqlite3", "iron-mcap-lz4"])
def test_plays_bags_of_other_writers(container: Any, tmp_path: Path, writer: str) -> None:
    node, client, process = container
    if writer.startswith("rosbags-"):
        storage, _, compression = writer.removeprefix("rosbags-").partition("-")
        bag = rosbags_bag(tmp_path / "bag", storage, compression)
    else:
        bag = legacy_bag(tmp_path / "bag", writer)
    handle = PlayerHandle(node, client, bag, topics=(("/chatter", "std_msgs/msg/String"),))
    stats = handle.wait_finished()
    assert stats["published"] == {"/chatter": 30}
    assert received(handle.report(), "/chatter") == [digest(chatter(n)) for n in range(30)]
    handle.unload()


# --- services ------------------------------------------------------------------------------------------------
def service_event_bag(path: Path) -> tuple[Path, list[bool]]:
    """A recorded SetBool service: for each call the four introspection events (client sent, service
    received, service responded, client received); returns the bag and the requests' values in order."""
    values = [n % 3 == 0 for n in range(6)]
    with BagWriter(path) as writer:
        writer.add_topic(TopicInfo("/set_flag/_service_event", "std_srvs/srv/SetBool_Event",
                                   offered_qos_profiles=[qos_profile_dict(RELIABLE)]))
        t = T0
        for value in values:
            for kind in (ServiceEventInfo.REQUEST_SENT, ServiceEventInfo.REQUEST_RECEIVED,
                         ServiceEventInfo.RESPONSE_SENT, ServiceEventInfo.RESPONSE_RECEIVED):
                event = SetBool.Event()
                event.info.event_type = kind
                if kind in (ServiceEventInfo.REQUEST_SENT, ServiceEventInfo.REQUEST_RECEIVED):
                    event.request = [SetBool.Request(data=value)]
                else:
                    event.response = [SetBool.Response(success=True, message="ok")]
                t += 10 * MS
                writer.write("/set_flag/_service_event", wire(event), t, t)
    return path, values


@pytest.mark.parametrize("source, events", [("SERVICE_INTROSPECTION", "received"),
                                            ("CLIENT_INTROSPECTION", "sent")])
def test_recorded_requests_are_sent_to_the_live_service(container: Any, tmp_path: Path, source: str,
                                                        events: str) -> None:
    """play.publish_service_request: each recorded request (of the chosen side) calls the service once."""
    node, client, process = container
    bag, values = service_event_bag(tmp_path / "bag")
    calls: list[bool] = []

    def serve(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        calls.append(request.data)
        response.success = True
        return response

    service = node.create_service(SetBool, "/set_flag", serve)
    try:
        handle = PlayerHandle(node, client, bag, {"play.publish_service_request": True,
                                                  "play.service_requests_source": source,
                                                  "play.delay.sec": 2}, topics=())
        assert wait_until(lambda: len(calls) >= len(values), 20.0, node), calls
        wait_until(lambda: False, 1.0, node)  # nothing more arrives
        assert calls == values
        handle.unload()
    finally:
        node.destroy_service(service)


def test_service_events_are_published_and_filtered(container: Any, tmp_path: Path) -> None:
    """Without publish_service_request the event topic is played like any topic; services_to_filter and
    exclude_services_to_filter name the service, not the topic."""
    node, client, process = container
    bag, values = service_event_bag(tmp_path / "bag")
    topics = (("/set_flag/_service_event", "std_srvs/srv/SetBool_Event"),)
    handle = PlayerHandle(node, client, bag, {"play.services_to_filter": ["/set_flag"]}, topics=topics)
    assert handle.wait_finished()["published"] == {"/set_flag/_service_event": 4 * len(values)}
    assert len(received(handle.report(), "/set_flag/_service_event")) == 4 * len(values)
    handle.unload()
    excluded = PlayerHandle(node, client, bag, {"play.exclude_services_to_filter": ["/set_flag"]}, topics=topics)
    assert excluded.wait_finished()["published"] == {}
    excluded.unload()


@pytest.mark.parametrize("parameters, message", [
    ({}, "storage.uri"),
    ({"storage.uri": "/nonexistent/bag"}, "/nonexistent/bag"),
    ({"storage.storage_id": "rosbag1"}, "storage.storage_id"),
    ({"play.rate": 0.0}, "play.rate"),
    ({"play.regex_to_filter": "("}, "play.regex_to_filter"),
    ({"play.read_ahead_queue_size": 0}, "play.read_ahead_queue_size"),
    ({"play.start_offset.nsec": 2_000_000_000}, "play.start_offset.nsec"),
    ({"play.service_requests_source": "BOTH"}, "play.service_requests_source"),
])
def test_bad_parameters_are_named_and_the_container_stays(container: Any, tmp_path: Path,
                                                           parameters: dict[str, Any], message: str) -> None:
    node, client, process = container
    bag = write_bag(tmp_path / "bag", regular_plan(3))
    full = {"storage.uri": str(bag), **parameters} if "storage.uri" not in parameters and parameters else parameters
    response = client.load(PLAYER, name="bad_player", extra=IPC, parameters=full)
    assert not response.success
    assert message in response.error_message, response.error_message
    assert client.list() is not None
