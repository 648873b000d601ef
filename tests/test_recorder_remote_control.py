"""rosbag2's remote control of the recorder: ``~/record``, ``~/stop``, ``~/start_discovery``, ``~/stop_discovery``
and ``~/is_discovery_running`` (rosbag2_interfaces as rosbag2 Jazzy 0.26.10 defines and answers them).

In-process: a container's manager with one recorder, driven by real rclpy service clients from a node in the same
context; the messages come over DDS from a plain rclpy node in a context of its own, and every bag is read back
with rosbags.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

import pytest
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbag2_interfaces.srv import IsDiscoveryRunning, Record, StartDiscovery, Stop, StopDiscovery
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from std_msgs.msg import String

from component_container.component_manager import ComponentManager
from component_container.startup_file import load_request
from components.recorder.recorder import Recorder
from ipc_testing import call, in_process_manager, wait_until
from ipc_testing.process_context import process_context

RECORDER = "remote_control_recorder"
CHATTER = "/remote_control/chatter"
KEPT = "/remote_control/kept"
LATE = "/remote_control/late"
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


@pytest.fixture()
def manager() -> Iterator[ComponentManager]:
    with in_process_manager("remote_control_test") as manager:
        yield manager


@pytest.fixture()
def client(manager: ComponentManager) -> Iterator[Node]:
    node = Node("remote_control_client", context=manager.context)
    try:
        yield node
    finally:
        node.destroy_node()


@pytest.fixture()
def talker() -> Iterator[Node]:
    """A plain rclpy node, not the container's: its messages reach the recorder over DDS, as another process's
    would."""
    node = Node("remote_control_talker", context=process_context())
    try:
        yield node
    finally:
        node.destroy_node()


def load_recorder(manager: ComponentManager, uri: Path, **parameters: Any) -> Recorder:
    loaded = manager.load(load_request({"package": "components", "plugin": "components::Recorder",
                                        "name": RECORDER, "parameters": {"storage.uri": str(uri), **parameters}}, 1))
    return loaded.node


def request(node: Node, srv_type: Any, service: str, **fields: Any) -> Any:
    """One call of the recorder's ``~/<service>`` by a real rclpy client."""
    client = node.create_client(srv_type, f"/{RECORDER}/{service}")
    try:
        return call(node, client, srv_type.Request(**fields))
    finally:
        node.destroy_client(client)


def written(recorder: Recorder, topic: str) -> int:
    current = recorder.stats()["current"]
    return current["topics"].get(topic, {}).get("written", 0) if current else 0


def publish(publisher: Any, recorder: Recorder, numbers: range) -> None:
    """Publish ``numbers`` as strings, each once the recorder has written the one before (no queue overflows)."""
    topic = publisher.topic_name
    for number in numbers:
        before = written(recorder, topic)
        publisher.publish(String(data=str(number)))
        assert wait_until(lambda: written(recorder, topic) > before, 10.0), f"{topic} {number} never written"


def subscribed(publisher: Any) -> bool:
    return bool(wait_until(lambda: publisher.get_subscription_count() >= 1, 20.0))


def bag_strings(bag: Path) -> dict[str, list[str]]:
    """Per topic, the strings rosbags reads from the bag, in order."""
    messages: dict[str, list[str]] = {}
    with Reader(bag) as reader:
        for connection, _, raw in reader.messages():
            messages.setdefault(connection.topic, []).append(
                TYPESTORE.deserialize_cdr(raw, connection.msgtype).data)
    return messages


def test_stop_then_record_under_a_new_uri_makes_two_complete_bags(manager: ComponentManager, client: Node,
                                                                   talker: Node, tmp_path: Path) -> None:
    first, second = tmp_path / "first", tmp_path / "second"
    recorder = load_recorder(manager, first, **{"record.topics": [CHATTER]})
    chatter = talker.create_publisher(String, CHATTER, RELIABLE)
    assert subscribed(chatter)
    publish(chatter, recorder, range(0, 30))

    request(client, Stop, "stop")  # Jazzy's Stop has an empty response
    assert recorder.stats()["recording"] is False
    assert request(client, IsDiscoveryRunning, "is_discovery_running").running is False
    request(client, Stop, "stop")  # not recording: logged and ignored, the recorder stays loaded

    started = request(client, Record, "record", uri=str(second))
    assert (started.return_code, started.error_string) == (0, "")
    refused = request(client, Record, "record", uri=str(tmp_path / "third"))
    assert refused.return_code == 1 and "already in recording" in refused.error_string, refused
    assert not (tmp_path / "third").exists()
    assert request(client, IsDiscoveryRunning, "is_discovery_running").running is True
    publish(chatter, recorder, range(30, 60))
    request(client, Stop, "stop")

    assert bag_strings(first) == {CHATTER: [str(n) for n in range(0, 30)]}
    assert bag_strings(second) == {CHATTER: [str(n) for n in range(30, 60)]}
    finals = recorder.stats()["finished"]
    assert [bag["bag"] for bag in finals] == [str(first), str(second)]
    for final, count in zip(finals, (30, 30)):
        assert final["topics"][CHATTER] | {"rate_limited": 0} == {
            "received": count, "written": count, "dropped": 0, "queue_dropped": 0, "rate_limited": 0,
            "repeated": 0}, final

    # An empty uri means the previous bag's; it exists, so rosbag2 appends "(1)".
    again = request(client, Record, "record", uri="")
    assert again.return_code == 0, again.error_string
    assert recorder.stats()["current"]["bag"] == str(tmp_path / "second(1)")
    publish(chatter, recorder, range(60, 65))
    request(client, Stop, "stop")
    assert bag_strings(tmp_path / "second(1)") == {CHATTER: [str(n) for n in range(60, 65)]}


def test_record_outside_the_bag_root_is_refused_with_the_reason(tmp_path: Path) -> None:
    root = tmp_path / "root"
    root.mkdir()
    with in_process_manager("remote_control_root", bag_root=root.resolve()) as manager:
        client = Node("remote_control_root_client", context=manager.context)
        try:
            recorder = load_recorder(manager, Path("inside"), **{"record.topics": [CHATTER]})
            request(client, Stop, "stop")
            refused = request(client, Record, "record", uri=str(tmp_path / "outside"))
            assert refused.return_code == 1 and "storage.uri" in refused.error_string, refused
            assert recorder.stats()["recording"] is False and not (tmp_path / "outside").exists()
            started = request(client, Record, "record", uri="elsewhere")
            assert started.return_code == 0, started.error_string
            assert recorder.stats()["current"]["bag"] == str(root.resolve() / "elsewhere")
        finally:
            client.destroy_node()


def test_stop_discovery_leaves_a_new_topic_out_until_start_discovery(manager: ComponentManager, client: Node,
                                                                     talker: Node, tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    recorder = load_recorder(manager, bag, **{"record.regex": "^/remote_control/"})
    kept = talker.create_publisher(String, KEPT, RELIABLE)
    assert subscribed(kept)
    assert request(client, IsDiscoveryRunning, "is_discovery_running").running is True
    publish(kept, recorder, range(0, 5))

    stopped = request(client, StopDiscovery, "stop_discovery")
    assert (stopped.return_code, stopped.error_string) == (0, "")
    again = request(client, StopDiscovery, "stop_discovery")
    assert (again.return_code, again.error_string) == (1, "Discovery is not running.")
    assert request(client, IsDiscoveryRunning, "is_discovery_running").running is False

    late = talker.create_publisher(String, LATE, RELIABLE)
    assert wait_until(lambda: LATE in dict(recorder.get_topic_names_and_types()), 20.0)
    recorder._discover_topics()  # the poll the discovery timer runs: the recorder sees the topic and leaves it
    assert late.get_subscription_count() == 0
    late.publish(String(data="while discovery was stopped"))
    publish(kept, recorder, range(5, 10))  # subscribed topics go on recording

    started = request(client, StartDiscovery, "start_discovery")
    assert (started.return_code, started.error_string) == (0, "")
    again = request(client, StartDiscovery, "start_discovery")
    assert (again.return_code, again.error_string) == (1, "Discovery is already running.")
    assert request(client, IsDiscoveryRunning, "is_discovery_running").running is True
    assert subscribed(late)
    publish(late, recorder, range(0, 3))
    request(client, Stop, "stop")

    assert bag_strings(bag) == {KEPT: [str(n) for n in range(0, 10)], LATE: ["0", "1", "2"]}
    # Not recording: discovery is off and cannot be started (rosbag2: "Recorder is not currently recording.").
    assert request(client, IsDiscoveryRunning, "is_discovery_running").running is False
    refused = request(client, StartDiscovery, "start_discovery")
    assert (refused.return_code, refused.error_string) == (1, "Recorder is not currently recording.")
