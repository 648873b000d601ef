"""Recording services as rosbag2 Jazzy does: service event topics (``<service>/_service_event``, type
``pkg/srv/Name_Event``) chosen by ``record.all_services`` / ``record.services`` / ``record.exclude_services``
(and the regexes, on the service name), stored as topics of their event type, and listed by ``bag info``
as services.

The bags are read back by ``rosbags`` (AnyReader: it parses every definition and checks its RIHS01 hash
against the topic's, so a wrong schema fails the whole bag) and by the ``mcap`` reader, whose raw event
bytes are decoded by rclpy. The recording test runs a real container and an out-of-process node
(tests/introspection_node.py) whose services and clients publish their events with introspection CONTENTS.
"""
from __future__ import annotations

import json
import queue
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
import yaml
from mcap.reader import make_reader
from rclpy.node import Node
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.highlevel import AnyReader
from service_msgs.msg import ServiceEventInfo
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger

from baglib.tools.info import format_bag_info
from baglib.format.message_definitions import MessageDefinitionNotFoundError, message_definition, type_hash
from baglib.format.metadata import TopicInfo
from baglib.format.service_events import (
    event_class,
    event_topic,
    event_type,
    is_service_event_topic,
    service_name,
    service_type,
)
from baglib.write.writer import BagWriter
from components.recorder.recorder_options import RecordOptions
from components.recorder.topic_selection import TopicFilter

from container_process import Containers, call, wait_until

HERE = Path(__file__).resolve().parent
IPC_COMPONENT = Path(sys.executable).with_name("ipc-component")
SET_FLAG_EVENTS = "/set_flag/_service_event"
TRIGGER_EVENTS = "/trigger_me/_service_event"
SET_FLAG_EVENT_TYPE = "std_srvs/srv/SetBool_Event"
TRIGGER_EVENT_TYPE = "std_srvs/srv/Trigger_Event"
CALLS = 3
EVENTS_PER_CALL = 4  # REQUEST_SENT and RESPONSE_RECEIVED by the client, REQUEST_RECEIVED and RESPONSE_SENT by the server
T0 = 1_700_000_000_000_000_000


# --- names ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("topic", "type_name", "expected"), [
    ("/abc/_service_event", "package/srv/xyz_Event", True),
    ("/ns/abc/_service_event", "package/srv/xyz_Event", True),
    ("/_service_event", "package/srv/xyz_Event", False),  # no service name before the suffix
    ("/abc/service_event", "package/srv/xyz_Event", False),
    ("/abc/_service_event", "package/xyz_Event", False),  # not a srv type
    ("/abc/_service_event", "package/srv/xyz", False),  # not an event type
    ("/abc/_service_event", "std_msgs/msg/String", False),
])
def test_service_event_topics_are_recognised_by_name_and_type(topic: str, type_name: str, expected: bool) -> None:
    assert is_service_event_topic(topic, type_name) is expected


def test_service_names_and_event_topics_map_both_ways() -> None:
    assert service_name("/abc/_service_event") == "/abc"
    assert service_name("/ns/abc/_service_event") == "/ns/abc"
    assert event_topic("/abc") == "/abc/_service_event"
    assert event_topic("/a/_service_event") == "/a/_service_event"  # already an event topic: unchanged
    assert event_topic("abc") == "abc/_service_event"  # relative stays relative
    for bad in ("/_service_event", "/abc/service_event", "/abc"):
        with pytest.raises(ValueError, match="not a service event topic"):
            service_name(bad)
    with pytest.raises(ValueError, match="must not be empty"):
        event_topic("")


def test_service_types_and_event_types_map_both_ways() -> None:
    assert service_type("example_interfaces/srv/AddTwoInts_Event") == "example_interfaces/srv/AddTwoInts"
    assert event_type("example_interfaces/srv/AddTwoInts") == "example_interfaces/srv/AddTwoInts_Event"
    for bad in ("package/xyz_Event", "package/srv/Event", "package/srv/xyz", "package/msg/xyz_Event"):
        with pytest.raises(ValueError, match="not a service event type"):
            service_type(bad)
    for bad in ("package/msg/xyz", "package/xyz", "package/srv/"):
        with pytest.raises(ValueError, match="not a service type"):
            event_type(bad)


def test_event_class_is_the_services_generated_event_message() -> None:
    assert event_class(SET_FLAG_EVENT_TYPE) is SetBool.Event
    assert event_class(TRIGGER_EVENT_TYPE) is Trigger.Event
    with pytest.raises(ModuleNotFoundError):
        event_class("no_such_package/srv/Nothing_Event")
    with pytest.raises(AttributeError):
        event_class("std_srvs/srv/Nothing_Event")
    with pytest.raises(ValueError):
        event_class("std_msgs/msg/String")


# --- selection (rosbag2 Jazzy's TopicFilter) --------------------------------------------------------------
EVENT = (SET_FLAG_EVENTS, SET_FLAG_EVENT_TYPE)
TOPIC = ("/chatter", "std_msgs/msg/String")
NOT_EVENT = ("/x/_service_event", "std_msgs/msg/String")  # an event topic's name, but not its type


@pytest.mark.parametrize(("options", "topic", "expected"), [
    # the topic options never take a service event topic, although its name is hidden
    ({"all_topics": True}, EVENT, False),
    ({"all_topics": True, "include_hidden_topics": True}, EVENT, False),
    ({"topics": [SET_FLAG_EVENTS]}, EVENT, False),
    ({"topic_types": [SET_FLAG_EVENT_TYPE]}, EVENT, False),
    ({"all_topics": True}, TOPIC, True),
    # the service options take only service event topics
    ({"all_services": True}, EVENT, True),
    ({"all_services": True}, TOPIC, False),
    ({"all_services": True}, NOT_EVENT, False),
    ({"all_topics": True, "include_hidden_topics": True}, NOT_EVENT, True),
    ({"services": ["/set_flag"]}, EVENT, True),
    ({"services": ["set_flag"]}, EVENT, True),
    ({"services": [SET_FLAG_EVENTS]}, EVENT, True),
    ({"services": ["/other"]}, EVENT, False),
    ({"all_services": True, "exclude_services": ["/set_flag"]}, EVENT, False),
    ({"all_services": True, "exclude_services": ["set_flag/_service_event"]}, EVENT, False),
    ({"all_services": True, "exclude_topics": [SET_FLAG_EVENTS]}, EVENT, True),
    ({"all_services": True, "exclude_topic_types": [SET_FLAG_EVENT_TYPE]}, EVENT, True),
    # the regexes see the service's name, not the event topic's
    ({"regex": "^/set_flag$"}, EVENT, True),
    ({"regex": "_service_event"}, EVENT, False),
    ({"all_services": True, "exclude_regex": "^/set"}, EVENT, False),
    ({"all_services": True, "exclude_regex": "_service_event$"}, EVENT, True),
    ({"regex": "^/chat"}, TOPIC, True),
])
def test_service_events_are_selected_as_rosbag2_jazzy_selects_them(options: dict[str, Any], topic: tuple[str, str],
                                                                    expected: bool) -> None:
    assert TopicFilter(RecordOptions(**options), set()).selects(*topic, publisher_count=1) is expected


def test_a_service_without_event_publishers_needs_include_unpublished_topics() -> None:
    assert not TopicFilter(RecordOptions(all_services=True), set()).selects(*EVENT, publisher_count=0)
    options = RecordOptions(all_services=True, include_unpublished_topics=True)
    assert TopicFilter(options, set()).selects(*EVENT, publisher_count=0)


# --- definitions and readers ------------------------------------------------------------------------------
def set_flag_event(event: int, data: bool, sequence: int) -> SetBool.Event:
    message = SetBool.Event()
    message.info.event_type = event
    message.info.sequence_number = sequence
    message.info.client_gid = list(range(16))
    if event in (ServiceEventInfo.REQUEST_SENT, ServiceEventInfo.REQUEST_RECEIVED):
        message.request = [SetBool.Request(data=data)]
    else:
        message.response = [SetBool.Response(success=data, message=f"reply {sequence}")]
    return message


def rosbags_messages(bag: Path) -> dict[str, list[Any]]:
    """Every message of the bag, decoded by rosbags' AnyReader from the bag's own definitions."""
    found: dict[str, list[Any]] = {}
    with AnyReader([bag]) as reader:
        for connection, _, raw in reader.messages():
            found.setdefault(connection.topic, []).append(reader.deserialize(raw, connection.msgtype))
    return found


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_event_definitions_decode_in_rosbags_and_match_rosidls_hash(tmp_path: Path, storage: str) -> None:
    """A bag written by BagWriter with service event topics (one with message dependencies) and a plain
    topic: rosbags parses the definitions, recomputes rosidl's RIHS01 hashes and decodes every event."""
    from rcl_interfaces.msg import ListParametersResult
    from rcl_interfaces.srv import ListParameters

    writer = BagWriter(tmp_path / "bag", storage_id=storage)
    writer.add_topic(TopicInfo(SET_FLAG_EVENTS, SET_FLAG_EVENT_TYPE))
    writer.add_topic(TopicInfo("/node/list_parameters/_service_event", "rcl_interfaces/srv/ListParameters_Event"))
    writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String"))
    events = [set_flag_event(kind, kind % 2 == 0, 1) for kind in range(4)]
    for i, event in enumerate(events):
        writer.write(SET_FLAG_EVENTS, serialize_message(event), T0 + i, T0 + i)
    parameters = ListParameters.Event()
    parameters.info.event_type = ServiceEventInfo.RESPONSE_SENT
    parameters.response = [ListParameters.Response(result=ListParametersResult(names=["camera.fps"]))]
    writer.write("/node/list_parameters/_service_event", serialize_message(parameters), T0 + 5, T0 + 5)
    writer.write("/chatter", serialize_message(String(data="hello")), T0 + 6, T0 + 6)
    writer.close()

    topics = {t["topic_metadata"]["name"]: t["topic_metadata"]
              for t in yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())
              ["rosbag2_bagfile_information"]["topics_with_message_count"]}
    assert topics[SET_FLAG_EVENTS]["type_description_hash"] == type_hash(SET_FLAG_EVENT_TYPE) == \
        "RIHS01_3c4c20015afb4303eafd347b1d6a786f171a89c814726961a9593ef10df878cf"  # std_srvs/srv/SetBool.json
    decoded = rosbags_messages(tmp_path / "bag")  # AnyReader fails on any hash mismatch or unparsable schema
    assert [(m.info.event_type, m.info.sequence_number, list(m.info.client_gid)) for m in decoded[SET_FLAG_EVENTS]] \
        == [(kind, 1, list(range(16))) for kind in range(4)]
    assert [[r.data for r in m.request] for m in decoded[SET_FLAG_EVENTS]] == [[True], [False], [], []]
    assert [[(r.success, r.message) for r in m.response] for m in decoded[SET_FLAG_EVENTS]] == \
        [[], [], [(True, "reply 1")], [(False, "reply 1")]]
    (reply,) = decoded["/node/list_parameters/_service_event"][0].response
    assert reply.result.names == ["camera.fps"]
    assert decoded["/chatter"][0].data == "hello"


def test_event_schema_is_the_event_message_in_idl(tmp_path: Path) -> None:
    """The MCAP schema is named after the event type (as rosbag2 names it) and describes the event message
    itself, not the .srv text rosbag2 Jazzy stores (ros2/rosbag2#2365)."""
    writer = BagWriter(tmp_path / "bag")
    writer.add_topic(TopicInfo(SET_FLAG_EVENTS, SET_FLAG_EVENT_TYPE))
    writer.close()
    with open(tmp_path / "bag" / "bag_0.mcap", "rb") as file:
        summary = make_reader(file).get_summary()
    (schema,) = summary.schemas.values()
    assert (schema.name, schema.encoding) == (SET_FLAG_EVENT_TYPE, "ros2idl")
    text = schema.data.decode()
    assert text == message_definition(SET_FLAG_EVENT_TYPE)[1]
    headers = [line for line in text.splitlines() if line.startswith("IDL: ")]
    assert headers == ["IDL: std_srvs/srv/SetBool_Event", "IDL: service_msgs/msg/ServiceEventInfo",
                       "IDL: builtin_interfaces/msg/Time", "IDL: std_srvs/srv/SetBool"]
    assert "sequence<std_srvs::srv::SetBool_Request, 1> request;" in text
    assert "#include" not in text  # rosbags' IDL parser rejects them; every included type is a section
    (channel,) = summary.channels.values()
    assert channel.metadata["topic_type_hash"] == type_hash(SET_FLAG_EVENT_TYPE)


def test_an_event_type_whose_service_is_not_installed_has_no_definition() -> None:
    with pytest.raises(MessageDefinitionNotFoundError, match="no message definition for no_pkg/srv/Nothing_Event"):
        message_definition("no_pkg/srv/Nothing_Event")
    with pytest.raises(MessageDefinitionNotFoundError, match="no type description"):
        type_hash("no_pkg/srv/Nothing_Event")


# --- bag info ---------------------------------------------------------------------------------------------
def test_bag_info_lists_services_apart_from_topics(tmp_path: Path) -> None:
    writer = BagWriter(tmp_path / "bag")
    writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String"))
    writer.add_topic(TopicInfo(SET_FLAG_EVENTS, SET_FLAG_EVENT_TYPE))
    writer.add_topic(TopicInfo(TRIGGER_EVENTS, TRIGGER_EVENT_TYPE))
    writer.add_topic(TopicInfo("/x/_service_event", "std_msgs/msg/String"))  # named like one, typed otherwise
    writer.write("/chatter", serialize_message(String(data="a")), T0, T0)
    for i in range(4):
        writer.write(SET_FLAG_EVENTS, serialize_message(set_flag_event(i, True, 1)), T0 + i, T0 + i)
    writer.close()
    lines = format_bag_info(tmp_path / "bag").splitlines()
    assert lines[7:] == [
        "Messages:          1",  # without the 4 service events, as rosbag2 counts
        "Topic information: Topic: /chatter | Type: std_msgs/msg/String | Count: 1 | Serialization Format: cdr",
        "                   Topic: /x/_service_event | Type: std_msgs/msg/String | Count: 0 | "
        "Serialization Format: cdr",
        "Services:          2",
        "Service information: Service: /set_flag | Type: std_srvs/srv/SetBool | Event Count: 4 | "
        "Serialization Format: cdr",
        "                     Service: /trigger_me | Type: std_srvs/srv/Trigger | Event Count: 0 | "
        "Serialization Format: cdr",
        "Actions:           0",
        "Action information:",
    ]


def test_bag_info_of_a_bag_without_services(tmp_path: Path) -> None:
    writer = BagWriter(tmp_path / "bag")
    writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String"))
    writer.close()
    assert format_bag_info(tmp_path / "bag").splitlines()[-4:] == ["Services:          0", "Service information:",
                                                                    "Actions:           0", "Action information:"]


# --- recording from a live graph ---------------------------------------------------------------------------
#: recorder name -> (its parameters, the topics its bag must hold: name -> message count)
RECORDERS: dict[str, tuple[dict[str, Any], dict[str, int]]] = {
    "all_services": ({"record.all_services": True},
                     {SET_FLAG_EVENTS: CALLS * EVENTS_PER_CALL, TRIGGER_EVENTS: CALLS * EVENTS_PER_CALL}),
    "one_service": ({"record.services": ["set_flag"], "record.topics": ["/chatter"]},
                    {SET_FLAG_EVENTS: CALLS * EVENTS_PER_CALL, "/chatter": CALLS}),
    "topics_only": ({"record.all_topics": True, "record.include_hidden_topics": True,
                     "record.exclude_regex": "^/(rosout|parameter_events|diagnostics|events/.*)$"},
                    {"/chatter": CALLS}),
    "excluded": ({"record.all_services": True, "record.exclude_services": ["/trigger_me"],
                  "storage.storage_id": "sqlite3"},
                 {SET_FLAG_EVENTS: CALLS * EVENTS_PER_CALL}),
    "service_regex": ({"record.regex": "_me$"},  # matches the service /trigger_me, not its event topic
                      {TRIGGER_EVENTS: CALLS * EVENTS_PER_CALL}),
}


class IntrospectionNode:
    """tests/introspection_node.py as a subprocess, driven line by line; killed by pid when left running.

    Its output is read by a thread into a queue, so that waiting for an answer has a deadline.
    """

    def __init__(self) -> None:
        self.process = subprocess.Popen([sys.executable, str(HERE / "introspection_node.py")], stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self._lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        self.expect("ready", timeout=30.0)

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self._lines.put(line)
        self._lines.put("")  # end of output

    def command(self, line: str, answer: str, timeout: float = 30.0) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write(line + "\n")
        self.process.stdin.flush()
        self.expect(answer, timeout)

    def expect(self, answer: str, timeout: float) -> None:
        """Wait for the line ``answer``; any other answer, the end of output or the deadline fails."""
        deadline = time.monotonic() + timeout
        seen: list[str] = []
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self._lines.get(timeout=left)
            except queue.Empty:
                break
            seen.append(line)
            if line.strip() == answer:
                return
            if line.strip() in ("ready", "matched", "timeout", "done") or not line:
                break
        raise AssertionError(f"introspection node did not answer {answer!r}; it printed:\n{''.join(seen)}")

    def close(self) -> None:
        """Close its input (it exits); kill it by pid if it does not."""
        if self.process.poll() is None:
            assert self.process.stdin is not None
            self.process.stdin.close()
            try:
                self.process.wait(timeout=10.0)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def received(probe: Node, recorder: str) -> dict[str, int]:
    """Messages the recorder received per topic so far (its ~/get_stats)."""
    client = probe.create_client(Trigger, f"/{recorder}/get_stats")
    try:  # sent again until answered: Fast DDS drops the reply to a client the service has not matched yet
        current = json.loads(call(probe, client, Trigger.Request(), 10.0, again=True).message)["current"]
        return {topic: counts["received"] for topic, counts in current["topics"].items()}
    finally:
        probe.destroy_client(client)


def test_recorders_record_service_events_as_selected(tmp_path: Path, probe: Node, containers: Containers) -> None:
    # The recorders list the publishers the graph shows when they subscribe: wait out any a finished test's
    # process may still have there (a participant is gone from the graph only once its removal is processed).
    def stale() -> list[tuple[str, str]]:
        return [(p.node_name, p.node_namespace) for topic in (SET_FLAG_EVENTS, TRIGGER_EVENTS)
                for p in probe.get_publishers_info_by_topic(topic)]
    assert wait_until(lambda: not stale(), 30.0), stale()
    _, container = containers.start()
    ids = {}
    for name, (parameters, _) in RECORDERS.items():
        response = container.load("components::Recorder", name=name,
                                  parameters={"storage.uri": str(tmp_path / name), **parameters})
        assert response.success, response.error_message
        ids[name] = response.unique_id
    node = IntrospectionNode()
    try:
        # transient_local events reach a late subscriber too; waiting for the subscriptions keeps this test
        # about selection, not discovery: 3 recorders take /set_flag's events, 2 /trigger_me's, 2 /chatter
        for topic, subscribers in ((SET_FLAG_EVENTS, 3), (TRIGGER_EVENTS, 2), ("/chatter", 2)):
            node.command(f"wait {topic} {subscribers}", "matched")
        node.command(f"call {CALLS}", "done")
        for name, (_, expected) in RECORDERS.items():
            counts = wait_until(lambda: (c := received(probe, name)) == expected and c, 20.0, interval=0.05)
            assert counts == expected, f"recorder {name} received {received(probe, name)}, expected {expected}"
        graph = [(p.node_name, p.node_namespace, str(p.qos_profile.durability))
                 for topic in (SET_FLAG_EVENTS, TRIGGER_EVENTS) for p in probe.get_publishers_info_by_topic(topic)]
        for name, unique_id in ids.items():
            assert container.unload(unique_id).success, name
    finally:
        node.close()

    for name, (_, expected) in RECORDERS.items():
        metadata = yaml.safe_load((tmp_path / name / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        listed = {t["topic_metadata"]["name"]: t for t in metadata["topics_with_message_count"]}
        assert {topic: entry["message_count"] for topic, entry in listed.items()} == expected, name
        for topic in set(expected) & {SET_FLAG_EVENTS, TRIGGER_EVENTS}:
            meta = listed[topic]["topic_metadata"]
            assert meta["type"] == (SET_FLAG_EVENT_TYPE if topic == SET_FLAG_EVENTS else TRIGGER_EVENT_TYPE)
            assert meta["type_description_hash"] == type_hash(meta["type"])  # as the publishers announced it
            # The publishers the recorder saw when it subscribed (as rosbag2, not updated later): the server's and
            # the client's, or only the first of them when its discovery ran between the two announcements.
            durabilities = [q["durability"] for q in meta["offered_qos_profiles"]]
            assert durabilities in (["transient_local"], ["transient_local"] * 2), (meta["offered_qos_profiles"], graph)
        check_events(tmp_path / name, expected)

    check_mcap_events(tmp_path / "all_services" / "all_services_0.mcap")
    info = subprocess.run([str(IPC_COMPONENT), "bag", "info", str(tmp_path / "all_services")],
                          capture_output=True, text=True, timeout=60, check=True).stdout.splitlines()
    assert info[7:] == [
        "Messages:          0",
        "Topic information:",
        "Services:          2",
        f"Service information: Service: /set_flag | Type: std_srvs/srv/SetBool | Event Count: {CALLS * 4} | "
        "Serialization Format: cdr",
        f"                     Service: /trigger_me | Type: std_srvs/srv/Trigger | Event Count: {CALLS * 4} | "
        "Serialization Format: cdr",
        "Actions:           0",
        "Action information:",
    ]


def check_events(bag: Path, expected: dict[str, int]) -> None:
    """rosbags decodes the recorded events: every call's four events, with the request and the reply."""
    decoded = rosbags_messages(bag)
    assert {topic: len(messages) for topic, messages in decoded.items()} == expected
    if SET_FLAG_EVENTS in expected:
        events = decoded[SET_FLAG_EVENTS]
        assert Counter(m.info.event_type for m in events) == {kind: CALLS for kind in range(4)}
        assert sorted(m.info.sequence_number for m in events) == sorted(list(range(1, CALLS + 1)) * 4)
        requests = Counter((m.info.sequence_number, m.request[0].data) for m in events if m.request)
        assert requests == {(i + 1, i % 2 == 0): 2 for i in range(CALLS)}  # sent by the client, received by the server
        replies = Counter((m.info.sequence_number, m.response[0].success, m.response[0].message)
                          for m in events if m.response)
        assert replies == {(i + 1, i % 2 == 0, f"flag {'set' if i % 2 == 0 else 'cleared'}"): 2 for i in range(CALLS)}
    if TRIGGER_EVENTS in expected:
        events = decoded[TRIGGER_EVENTS]
        assert Counter(m.info.event_type for m in events) == {kind: CALLS for kind in range(4)}
        assert all(m.response[0].message == "triggered" for m in events if m.response)


def check_mcap_events(path: Path) -> None:
    """The mcap reader sees the channels and schemas rosbag2 would name, and rclpy decodes their bytes."""
    kinds: Counter[tuple[str, int]] = Counter()
    with open(path, "rb") as file:
        reader = make_reader(file)
        for schema, channel, message in reader.iter_messages():
            assert schema is not None and schema.encoding == "ros2idl"
            assert schema.data.decode() == message_definition(schema.name)[1]
            event = deserialize_message(message.data, event_class(schema.name))
            kinds[(channel.topic, event.info.event_type)] += 1
    assert kinds == {(topic, kind): CALLS for topic in (SET_FLAG_EVENTS, TRIGGER_EVENTS) for kind in range(4)}

