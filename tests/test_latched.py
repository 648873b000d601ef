"""Latched (transient_local) topics reach in-process subscribers that join late, as a late DDS reader gets them.

``/tf_static``, ``/robot_description`` and latched ``camera_info`` are published once, at start. A subscriber in
another process gets them from the publisher's DDS history; one in the same container gets them from the
intra-process manager's history (its DDS reader drops the DDS copy as a local sample): once, in publish order,
the newest up to its own depth, and only if it asked for transient_local itself.

Real rclpy nodes over Fast DDS; "the container" is a context with an intra-process manager, or a
ComponentManager in this process (every executor model) for the recorder. tf2_msgs is not among the wheels,
so the latched topic is ``/robot_description`` (std_msgs/String), as robot_state_publisher publishes it.
"""
from __future__ import annotations

import sys
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import pytest
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from std_msgs.msg import String

from component_container.component_executors import EXECUTOR_KINDS
from component_container.component_manager import ComponentManager
from component_container.component_node import ComponentNode
from component_container.intra_process import IntraProcessManager, IntraProcessSubscription
from component_container.startup_file import load_request
from ipc_testing.process_context import process_context
from test_intra_process import spin_until

TOPIC = "/robot_description"
DESCRIPTION, UPDATED = "<robot name='r1'/>", "<robot name='r1' version='2'/>"
# The race: this many subscriptions join while a publisher keeping RACE_DEPTH messages publishes.
RACE_DEPTH, RACE_JOINS = 1000, 250


def latched(depth: int) -> QoSProfile:
    return QoSProfile(depth=depth, durability=DurabilityPolicy.TRANSIENT_LOCAL)


class RobotStatePublisher(ComponentNode):
    """Publishes the robot description once, at load, on a latched topic (as robot_state_publisher does)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("robot_state_publisher", **kwargs)
        self.publisher = self.create_publisher(String, TOPIC, latched(1))
        self.publisher.publish(String(data=DESCRIPTION))


class Container:
    """The nodes of one in-process container: the process's context and an intra-process manager; every node
    made here is destroyed with the container (a latched publisher left to the garbage collector would go on
    offering its history to the next test's subscribers)."""

    def __init__(self) -> None:
        self.context = process_context()
        self.ipm = IntraProcessManager()
        self.nodes: list[Node] = []

    def node(self, name: str) -> ComponentNode:
        return self.keep(ComponentNode(name, context=self.context, intra_process_manager=self.ipm))

    def keep(self, node: Node) -> Any:
        self.nodes.append(node)
        return node

    def close(self) -> None:
        for node in self.nodes:
            node.destroy_node()


@pytest.fixture
def container() -> Iterator[Container]:
    made = Container()
    yield made
    made.close()


def dds_witness(context: Context, topic: str, qos: QoSProfile) -> tuple[Node, list[str]]:
    """A plain DDS reader in the container's participant. Once it has a publisher's DDS history, the late
    in-process subscriptions' own DDS readers have had it too, and must not have delivered it again. The caller
    destroys it."""
    node = Node("dds_witness", context=context)
    got: list[str] = []
    node.create_subscription(String, topic, lambda m: got.append(m.data), qos)
    return node, got


# --- the recorder, in every executor model ----------------------------------------------------------------------
@pytest.mark.parametrize("kind", EXECUTOR_KINDS)
def test_a_recorder_loaded_after_a_latched_publisher_records_its_message(kind: str, tmp_path: Path) -> None:
    """The bag of a recorder loaded after the latched publish holds that message once, logged when the
    recorder got it (inside its window), then the next one published live; nothing twice over DDS."""
    context = process_context()
    manager = ComponentManager(kind, use_intra_process_comms=True, allow_module_plugins=True,
                               node_name=f"latched_{kind}", context=context)
    bag = tmp_path / "bag"
    witness: Node | None = None
    try:
        robot = manager.load(load_request({"package": "test_latched", "plugin": "test_latched:RobotStatePublisher"},
                                          1)).node
        loaded = manager.load(load_request({"package": "components", "plugin": "components::Recorder",
                                            "parameters": {"storage.uri": str(bag), "record.topics": [TOPIC]}}, 1))
        window_start = loaded.node.stats()["window_ns"][0]
        witness, seen = dds_witness(context, TOPIC, latched(1))
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(witness)
        assert spin_until(executor, lambda: seen == [DESCRIPTION], timeout=20), seen
        robot.publisher.publish(String(data=UPDATED))
        assert spin_until(executor, lambda: seen == [DESCRIPTION, UPDATED], timeout=20), seen
        executor.shutdown()
        unloaded = manager.unload(loaded.unique_id)
        assert unloaded.found and not unloaded.error, unloaded
    finally:
        if witness is not None:
            witness.destroy_node()
        manager.shutdown()
        manager.destroy_node()
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        messages = [(timestamp, store.deserialize_cdr(raw, connection.msgtype).data)
                    for connection, timestamp, raw in reader.messages()]
    assert [data for _, data in messages] == [DESCRIPTION, UPDATED]
    assert messages[0][0] >= window_start


# --- user components ------------------------------------------------------------------------------------------
def test_a_late_subscriber_gets_the_kept_messages_once_newest_up_to_its_depth(container: Container) -> None:
    """Publisher depth 5, eight published: a late depth-3 subscriber gets the newest 3, a keep_all one all 5
    kept, none counted as dropped; the next message reaches both once, after them; the DDS history that their
    own DDS readers also get is not delivered a second time."""
    publisher = container.node("map_server").create_publisher(String, "map", latched(5))
    for index in range(8):
        publisher.publish(String(data=str(index)))
    late = container.node("late")
    shallow: list[str] = []
    everything: list[str] = []
    shallow_sub = late.create_subscription(String, "map", lambda m: shallow.append(m.data), latched(3))
    late.create_subscription(String, "map", lambda m: everything.append(m.data),
                             QoSProfile(history=HistoryPolicy.KEEP_ALL, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    witness, seen = dds_witness(container.context, "map", latched(5))
    container.keep(witness)
    executor = SingleThreadedExecutor(context=container.context)
    executor.add_node(late)
    executor.add_node(witness)
    assert spin_until(executor, lambda: seen == ["3", "4", "5", "6", "7"], timeout=20), seen
    publisher.publish(String(data="8"))
    assert spin_until(executor, lambda: "8" in shallow and "8" in everything and "8" in seen, timeout=20)
    assert shallow == ["5", "6", "7", "8"]
    assert everything == ["3", "4", "5", "6", "7", "8"]
    assert shallow_sub.dropped_count == 0
    executor.shutdown()


def test_a_volatile_late_subscriber_gets_nothing_kept(container: Container) -> None:
    """As over DDS (and in rclcpp's intra-process manager): history is for transient_local subscribers only."""
    publisher = container.node("map_server").create_publisher(String, "map", latched(5))
    publisher.publish(String(data="kept"))
    late = container.node("late")
    got: list[str] = []
    late.create_subscription(String, "map", lambda m: got.append(m.data), 10)
    publisher.publish(String(data="live"))
    executor = SingleThreadedExecutor(context=container.context)
    executor.add_node(late)
    assert spin_until(executor, lambda: "live" in got)
    assert got == ["live"]
    executor.shutdown()


def test_kept_messages_are_received_when_replayed_and_go_with_their_publisher(container: Container) -> None:
    """A late subscriber's message info says what a late DDS reader's says: published then, received now. An
    inline, container-only subscription (the recorder's kind) gets them too; a publisher destroyed takes its
    history with it."""
    node = container.node("map_server")
    publisher = node.create_publisher(String, "map", latched(1))
    publisher.publish(String(data="kept"))
    joined = time.time_ns()
    late = container.node("late")
    infos: list[tuple[str, dict[str, Any]]] = []
    late.create_subscription(String, "map", lambda m, info: infos.append((m.data, info)), latched(1),
                             intra_process_inline=True, intra_process_only=True)
    assert [data for data, _ in infos] == ["kept"]
    assert infos[0][1]["source_timestamp"] < joined <= infos[0][1]["received_timestamp"]
    node.destroy_publisher(publisher)
    too_late: list[str] = []
    late.create_subscription(String, "map", lambda m: too_late.append(m.data), latched(1),
                             intra_process_inline=True, intra_process_only=True)
    assert too_late == []


def test_a_latched_message_the_player_publishes_with_nobody_listening_is_kept(container: Container) -> None:
    """The player publishes recorded bytes and makes an object only for in-process subscribers; on a latched
    topic it keeps one for those that join later."""
    publisher = container.node("player").create_publisher(String, TOPIC, latched(1))
    recorded = String(data=DESCRIPTION)
    publisher.publish_recorded(serialize_message(recorded), lambda: String(data=recorded.data))
    got: list[str] = []
    container.node("consumer").create_subscription(
        String, TOPIC, lambda m: got.append(m.data), latched(1), intra_process_inline=True, intra_process_only=True)
    assert got == [DESCRIPTION]


def test_late_joiners_racing_a_publisher_get_every_message_once_in_order() -> None:
    """Subscriptions join while a latched publisher publishes as fast as it can: each gets an unbroken run of
    its messages, the history and then live, none missing in between, none twice, none out of order."""
    ipm = IntraProcessManager()
    publication = ipm.add_publication("/burst", latched(RACE_DEPTH))
    subscribers: list[list[int]] = []
    stop = threading.Event()
    published = threading.Event()

    def publish() -> None:
        index = 0
        while not stop.is_set():
            ipm.deliver(publication, index)
            index += 1
            published.set()

    thread = threading.Thread(target=publish)
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # the GIL changes hands as often as it can: the windows between steps open
    thread.start()
    try:
        assert published.wait(10)
        for _ in range(RACE_JOINS):
            got: list[int] = []
            subscribers.append(got)
            ipm.add_subscription(IntraProcessSubscription(
                "/burst", latched(RACE_DEPTH), lambda: None,
                inline=lambda message, _stamps, got=got: got.append(message)))
    finally:
        stop.set()
        thread.join()
        sys.setswitchinterval(interval)
    for got in subscribers:
        assert got and got == list(range(got[0], got[0] + len(got))), (got[:10], len(got))
