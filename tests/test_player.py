"""``components::Player`` as users run it: a real container process, real Fast DDS, bags on disk.

Every test writes its bag with this project's BagWriter (or rosbags, for what BagWriter refuses to write),
loads a player into a container started with intra-process comms next to a ``PlaybackProbe`` (an in-process
subscriber that reports receive times and the CDR digest of each message), and checks what arrived: every
message, byte for byte, in bag order, never before its time in the schedule; the rosbag2 services against their
Jazzy behaviour; an out-of-process subscriber gets the recorded bytes over DDS.

Receive times are only checked from below ("not before its time": a loaded machine can only make a message
later): how punctual playback is, is the replay benchmark's measure (benchmarks/replay_bench.py), and the
arithmetic of the schedule (rate, pause, jump) is checked with a fake clock in test_playback_clock.py.
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


def assert_not_early(times: list[int], offsets: list[int], anchor: int, rate: float = 1.0) -> None:
    """Message k is received no earlier than ``anchor`` + ``offsets[k]`` / ``rate`` (steady ns), where ``anchor``
    is a moment before the run started (a request sent before it) and ``offsets`` are bag-time offsets from the
    run's first message: the player waited for every message's time. A machine stall only makes messages later,
    and the player's falling behind moves its schedule back, never forward, so the bound holds however loaded
    the machine is."""
    assert len(times) == len(offsets)
    early = [(k, (anchor + offset / rate - time) / MS) for k, (time, offset) in enumerate(zip(times, offsets))
             if time < anchor + offset / rate]
    assert not early, f"(message, ms too early): {early[:10]}"


def digest(data: bytes) -> str:
    return hashlib.sha1(data).hexdigest()


# --- the player through its services ------------------------------------------------------------------------
#: The player's services and their types. Clients of all of them are created before the player is loaded: a
#: service can only answer a client whose reply reader it has matched, which it does at once for one that exists
#: when it is created. IDEMPOTENT ones are sent again until answered (a lost reply then costs nothing); the
#: others (a second toggle, play_next, burst ... would act twice) are sent once.
SERVICES = {"is_paused": IsPaused, "pause": Pause, "resume": Resume, "toggle_paused": TogglePaused,
            "play_next": PlayNext, "burst": Burst, "set_rate": SetRate, "get_rate": GetRate, "seek": Seek,
            "stop": Stop, "play": Play, "get_stats": Trigger}
IDEMPOTENT = {"is_paused", "pause", "resume", "set_rate", "get_rate", "seek", "get_stats"}


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
        self.clients = {service: node.create_client(srv_type, f"/{name}/{service}")
                        for service, srv_type in SERVICES.items()}
        self.clients["report"] = node.create_client(Trigger, f"/{name}_probe/report")
        probe = client.load(PROBE, "tests", name=f"{name}_probe", extra=IPC,
                            parameters={"topics": [t for t, _ in topics] or [""],  # [] would be a byte array
                                        "types": [t for _, t in topics] or [""]})
        assert probe.success, probe.error_message
        self.probe_id = probe.unique_id
        self.load_sent = time.monotonic_ns()  # the run cannot start before this
        loaded = client.load(PLAYER, name=name, extra=IPC,
                             parameters={"storage.uri": str(bag), **(parameters or {})})
        assert loaded.success, loaded.error_message
        self.unique_id = loaded.unique_id

    def player(self, srv_type: Any, service: str, request: Any = None, timeout: float = 10.0) -> Any:
        client = self.clients[service]
        assert client.srv_type is srv_type
        return call(self.node, client, request or srv_type.Request(), timeout, again=service in IDEMPOTENT)

    def stats(self) -> dict[str, Any]:
        return json.loads(self.player(Trigger, "get_stats").message)

    def report(self) -> dict[str, Any]:
        return json.loads(call(self.node, self.clients["report"], Trigger.Request(), 10.0, again=True).message)

    def wait_finished(self, timeout: float = 20.0) -> dict[str, Any]:
        stats = wait_until(lambda: (s := self.stats()) and not s["playing"] and s, timeout)
        assert stats, f"playback did not finish within {timeout} s: {self.stats()}"
        return stats

    def unload(self) -> None:
        for unique_id in (self.unique_id, self.probe_id):
            if unique_id:
                assert self.client.unload(unique_id).success
        self.unique_id = self.probe_id = 0
        for service_client in self.clients.values():
            self.node.destroy_client(service_client)
        self.clients.clear()
        if self in PlayerHandle.live:
            PlayerHandle.live.remove(self)


@pytest.fixture(autouse=True)
def unload_players(container: Any) -> Any:
    """Whatever a test left loaded (it failed half-way) is unloaded before the next test starts, and the shared
    container must still run with nothing of the test left in it."""
    yield
    while PlayerHandle.live:
        PlayerHandle.live[-1].unload()
    node, client, process = container
    assert process.alive(), process.output[-3000:]
    assert client.list().full_node_names == [], client.list().full_node_names


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
    # Each message went out no earlier than its offset in the bag after the player was loaded.
    for topic in ("/chatter", "/image"):
        offsets = [offset for t, offset, _ in plan if t == topic]
        assert_not_early(report[topic]["times"], offsets, handle.load_sent)
    assert stats["publish_error_ms"]["count"] == 80
    handle.unload()


def test_delay_holds_the_start(container: Any, tmp_path: Path) -> None:
    """play.delay: the run starts that long after the load; none of its messages comes before."""
    node, client, process = container
    plan = [("/chatter", n * 10 * MS, chatter(n)) for n in range(5)]
    bag = write_bag(tmp_path / "bag", plan)
    delay = 500 * MS
    handle = PlayerHandle(node, client, bag, {"play.delay.sec": 0, "play.delay.nsec": delay},
                          topics=(("/chatter", "std_msgs/msg/String"),))
    handle.wait_finished()
    report = handle.report()
    assert received(report, "/chatter") == expected(plan, "/chatter")
    assert_not_early(report["/chatter"]["times"], [offset for _, offset, _ in plan], handle.load_sent + delay)
    handle.unload()


def test_out_of_process_subscriber_gets_the_recorded_bytes(container: Any, tmp_path: Path) -> None:
    node, client, process = container
    plan = regular_plan(30)
    bag = write_bag(tmp_path / "bag", plan)
    got: list[bytes] = []
    subscription = node.create_subscription(String, "/chatter", got.append, RELIABLE, raw=True)
    # As recorded, but for the zero padding Fast DDS appends to a raw sample to reach a multiple of 4 bytes
    # (rosbag2's player goes through the same rmw call, so its samples get the same padding).
    recorded = [data + bytes(-len(data) % 4) for topic, _, data in plan if topic == "/chatter"]

    def a_whole_pass() -> bool:
        # The player loops: however late the two processes match, a pass that starts after that is whole.
        starts = [i for i, data in enumerate(got) if data == recorded[0]]
        return any(got[i:i + len(recorded)] == recorded for i in starts)

    try:
        handle = PlayerHandle(node, client, bag, {"play.loop": True})
        assert wait_until(a_whole_pass, 20.0, node), f"{len(got)} received, no whole pass of {len(recorded)}"
        assert set(got) <= set(recorded), "bytes that are not in the bag"
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
    assert received(handle.report(), "/chatter") == []  # the first message was due at once: held
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
    """Rate 2 set while paused; then a pause holds bag time: after the resume no message comes before its time
    counted from the resume at twice the bag's pace (a clock that ran on while paused would publish the overdue
    ones at once); nothing is published while paused; every message once, in order."""
    node, client, process = container
    period = 50 * MS
    plan = [("/chatter", n * period, chatter(n)) for n in range(60)]  # 3 s of bag, 50 ms apart
    bag = write_bag(tmp_path / "bag", plan)
    handle = PlayerHandle(node, client, bag, {"play.start_paused": True}, topics=(("/chatter", "std_msgs/msg/String"),))
    assert handle.player(SetRate, "set_rate", SetRate.Request(rate=2.0)).success
    resumed = time.monotonic_ns()
    handle.player(Resume, "resume")
    assert wait_until(lambda: len(received(handle.report(), "/chatter")) >= 8, 10.0)
    handle.player(Pause, "pause")
    assert handle.player(IsPaused, "is_paused").paused
    held = len(received(handle.report(), "/chatter"))
    # The pause must last for the checks below to mean anything: 0.5 s is twenty messages at rate 2 that a clock
    # running on would find overdue at resume. No assertion depends on how long it really lasted.
    time.sleep(0.5)
    assert len(received(handle.report(), "/chatter")) == held, "published while paused"
    resumed_again = time.monotonic_ns()
    handle.player(Resume, "resume")
    stats = handle.wait_finished()
    assert stats["rate"] == 2.0
    report = handle.report()
    assert received(report, "/chatter") == expected(plan, "/chatter")
    times = report["/chatter"]["times"]
    assert_not_early(times[:held], [offset for _, offset, _ in plan[:held]], resumed, 2.0)
    # After the resume: counted from the first message published then (the player may have been up to one
    # period late with it when paused: its 'behind' threshold is far below that).
    first = plan[held][1] + period
    assert_not_early(times[held:], [max(0, offset - first) for _, offset, _ in plan[held:]], resumed_again, 2.0)


def test_stop_ends_playback_and_unload_mid_playback_is_clean(container: Any, tmp_path: Path) -> None:
    node, client, process = container
    plan = [("/chatter", n * 100 * MS, chatter(n)) for n in range(100)]  # 10 s
    bag = write_bag(tmp_path / "bag", plan)
    handle = PlayerHandle(node, client, bag, topics=(("/chatter", "std_msgs/msg/String"),))
    assert wait_until(lambda: len(received(handle.report(), "/chatter")) >= 3, 10.0)
    handle.player(Stop, "stop")
    stats = handle.stats()
    assert not stats["playing"]
    count = len(received(handle.report(), "/chatter"))
    assert count < 100
    # a new run from the start (a default request's zero duration would play nothing, as in rosbag2)
    assert handle.player(Play, "play", Play.Request(playback_duration=DurationMsg(sec=5))).success
    assert wait_until(lambda: len(received(handle.report(), "/chatter")) >= count + 3, 10.0)
    # The stopped run ended where it was stopped: what follows is the new run, from the first message again.
    got = received(handle.report(), "/chatter")
    digests = expected(plan, "/chatter")
    assert got[:count] == digests[:count] and got[count:] == digests[:len(got) - count], "the stopped run went on"
    handle.unload()  # mid-playback
    assert all(name != f"/{handle.name}" for name in client.list().full_node_names)


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
                                                  "play.start_paused": True, "play.rate": 5.0})
        assert wait_until(lambda: subscription.get_publisher_count() > 0, 10.0, node), "no read_split publisher"
        handle.player(Resume, "resume")
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
    handle = PlayerHandle(node, client, bag, {"play.rate": 10.0}, topics=(("/chatter", "std_msgs/msg/String"),))
    handle.wait_finished()
    got = received(handle.report(), "/chatter")
    assert 50 < len(got) < 200
    assert got == expected(plan, "/chatter")[: len(got)]
    handle.unload()
    assert process.alive()


# --- several bags as one timeline ---------------------------------------------------------------------------
def test_several_bags_play_as_one_timeline(container: Any, tmp_path: Path) -> None:
    """rosbag2 Kilted's ``play -i A -i B -i C``: one clock from the earliest start, the messages of all three in
    log-time order (a tie in the order the bags were named), the topics of every bag advertised; each split bag
    sends its own read_split events, none for moving between bags."""
    node, client, process = container
    plans = [[("/chatter", n * 15 * MS + index * 5 * MS, chatter(100 * index + n)) for n in range(12)]
             + [("/chatter", 400 * MS, chatter(100 * index + 99))] for index in range(3)]
    plans[1] = sorted(plans[1] + [("/image", n * 45 * MS, image(n, height=100)) for n in range(4)],
                      key=lambda entry: entry[1])  # only this bag has /image
    bags = [write_bag(tmp_path / f"bag{index}", plan, max_bagfile_size=12000 if index == 1 else 0)
            for index, plan in enumerate(plans)]
    split = sorted(str(path) for path in bags[1].glob("*.mcap"))
    assert len(split) >= 2
    events: list[ReadSplitEvent] = []
    subscription = node.create_subscription(ReadSplitEvent, "/events/read_split", events.append, 10)
    try:
        handle = PlayerHandle(node, client, bags[0], {"storage.uri": "", "storage.uris": [str(b) for b in bags],
                                                      "play.start_paused": True})
        assert wait_until(lambda: subscription.get_publisher_count() > 0, 10.0, node), "no read_split publisher"
        handle.player(Resume, "resume")
        stats = handle.wait_finished()
        merged = sorted((entry for plan in plans for entry in plan), key=lambda entry: entry[1])  # stable: bag order
        report = handle.report()
        assert received(report, "/chatter") == [digest(data) for topic, _, data in merged if topic == "/chatter"]
        assert received(report, "/image") == expected(plans[1], "/image")
        assert stats["duration_ns"] == 400 * MS and stats["bag"] == ", ".join(str(b) for b in bags)
        wait_until(lambda: len(events) >= len(split) - 1, 5.0, node)
        assert [(e.closed_file, e.opened_file) for e in events] == list(zip(split, split[1:]))
        handle.unload()
    finally:
        node.destroy_subscription(subscription)


def crossed_bag(path: Path, storage_id: str) -> list[tuple[int, int, bytes]]:
    """A /chatter bag whose publish times order each pair of messages the other way round from their receive
    times: message 2k+1 was published 10 ms before message 2k, and received 10 ms after it (a slow publisher's
    message overtaken in transport). Returns (receive offset, publish offset, CDR) in receive order."""
    plan = []
    for k in range(10):
        plan.append((60 * k * MS + 20 * MS, 60 * k * MS + 10 * MS, chatter(2 * k)))
        plan.append((60 * k * MS + 30 * MS, 60 * k * MS, chatter(2 * k + 1)))
    with BagWriter(path, storage_id=storage_id) as writer:
        writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String",
                                   offered_qos_profiles=[qos_profile_dict(RELIABLE)]))
        for received_at, published_at, data in plan:
            writer.write("/chatter", data, T0 + received_at, T0 + published_at)
    return plan


@pytest.mark.parametrize("order", ["RECEIVED_TIMESTAMP", "SENT_TIMESTAMP"])
def test_message_order_plays_by_receive_or_publish_time(container: Any, tmp_path: Path, order: str) -> None:
    """rosbag2 Kilted's ``play.message_order`` (#1876): the subscriber gets the messages in the order and at the
    times of the chosen timestamp. By publish time, the two messages published before the bag's start (its
    first receive time) go out at once, in publish order; every other one no earlier than its publish time."""
    node, client, process = container
    plan = crossed_bag(tmp_path / "bag", "mcap")
    handle = PlayerHandle(node, client, tmp_path / "bag", {"play.message_order": order},
                          topics=(("/chatter", "std_msgs/msg/String"),))
    handle.wait_finished()
    report = handle.report()
    start = plan[0][0]
    if order == "SENT_TIMESTAMP":
        by_time = sorted(plan, key=lambda entry: entry[1])
        offsets = [max(published - start, 0) for _, published, _ in by_time]
    else:
        by_time = plan
        offsets = [received_at - start for received_at, _, _ in plan]
    assert received(report, "/chatter") == [digest(data) for _, _, data in by_time]
    assert by_time != plan or order == "RECEIVED_TIMESTAMP"
    assert_not_early(report["/chatter"]["times"], offsets, handle.load_sent)
    handle.unload()


def test_a_bag_without_publish_times_plays_in_receive_order_either_way(container: Any, tmp_path: Path) -> None:
    """SQLite3 stores one timestamp per message (rosbag2's ``messages.timestamp``, the receive time): ordering
    by publish time is then ordering by receive time, as rosbag2's send_timestamp falls back to recv_timestamp."""
    node, client, process = container
    plan = crossed_bag(tmp_path / "bag", "sqlite3")
    handle = PlayerHandle(node, client, tmp_path / "bag", {"play.message_order": "SENT_TIMESTAMP"},
                          topics=(("/chatter", "std_msgs/msg/String"),))
    handle.wait_finished()
    assert received(handle.report(), "/chatter") == [digest(data) for _, _, data in plan]
    handle.unload()


def test_bags_with_one_topic_of_two_types_are_refused(container: Any, tmp_path: Path) -> None:
    node, client, process = container
    strings = write_bag(tmp_path / "strings", [("/chatter", 0, chatter(0))])
    images = tmp_path / "images"
    with BagWriter(images) as writer:
        writer.add_topic(TopicInfo("/chatter", "sensor_msgs/msg/Image"))
        writer.write("/chatter", image(0), T0, T0)
    response = client.load(PLAYER, name="mixed_player", extra=IPC,
                           parameters={"storage.uris": [str(strings), str(images)]})
    assert not response.success
    assert all(text in response.error_message for text in ("storage.uris", "/chatter", str(strings), str(images)))


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
    handle = PlayerHandle(node, client, bag, {"play.rate": 10.0},  # what is read matters here, not when
                          topics=(("/chatter", "std_msgs/msg/String"),))
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
                                                  "play.start_paused": True}, topics=())
        # The player's client is in the graph (and finds this existing service at once): the requests can go.
        assert wait_until(lambda: node.count_clients("/set_flag") > 0, 10.0, node)
        handle.player(Resume, "resume")
        stats = handle.wait_finished()
        # It sent one request per recorded request event of the chosen side, and each arrived once, in order.
        assert stats["published"] == {"/set_flag/_service_event": len(values)}, stats
        assert wait_until(lambda: len(calls) >= len(values), 20.0, node), calls
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
    ({"storage.uris": ["/elsewhere/bag"]}, "'storage.uri' and 'storage.uris' are both set"),
    ({"storage.storage_ids": ["mcap", "mcap"]}, "storage.storage_ids"),
    ({"play.rate": 0.0}, "play.rate"),
    ({"play.regex_to_filter": "("}, "play.regex_to_filter"),
    ({"play.read_ahead_queue_size": 0}, "play.read_ahead_queue_size"),
    ({"play.start_offset.nsec": 2_000_000_000}, "play.start_offset.nsec"),
    ({"play.service_requests_source": "BOTH"}, "play.service_requests_source"),
    ({"play.message_order": "sent"}, "play.message_order"),
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
