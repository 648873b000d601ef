"""Recording and replaying actions as rosbag2 Kilted does (ros2/rosbag2#1939, #1955): ``record.actions`` /
``record.all_actions`` / ``record.exclude_actions`` take an action's feedback and status topics and its three services' event topics,
named and typed as Kilted stores them; ``bag info`` lists them as actions; on Jazzy the container's
``ComponentNode.create_action_server`` / ``create_action_client`` publish those events (Kilted's action
introspection); the player with ``play.send_actions_as_client`` sends the recorded goals to a running server.

The end-to-end test runs a real rclpy action server and client (test_msgs/action/Fibonacci) in a context of their
own, a recorder in an in-process container, and reads the bag back with rosbags (AnyReader: it parses every
definition and checks its RIHS01 hash against the topic's).
"""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import pytest
import rclpy
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.executors import MultiThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rclpy.service_introspection import ServiceIntrospectionState
from service_msgs.msg import ServiceEventInfo
from test_msgs.action import Fibonacci

from baglib.format.action_topics import action_name, action_topics, action_type, is_action_topic
from baglib.format.message_definitions import message_class, message_definition, type_hash
from baglib.format.metadata import TopicInfo
from baglib.tools.info import format_bag_info
from baglib.write.writer import BagWriter
from component_container.component_manager import ComponentManager
from component_container.component_node import ComponentNode
from component_container.startup_file import load_request
from components.recorder.recorder import Recorder
from components.recorder.recorder_options import RecordOptions
from components.recorder.topic_selection import TopicFilter
from ipc_testing import ContainerProcess, in_process_manager, wait_until
from ipc_testing.process_context import process_context
from test_service_recording import rosbags_messages

FIB = "/fibonacci"
SEND_GOAL = "/fibonacci/_action/send_goal/_service_event"
CANCEL_GOAL = "/fibonacci/_action/cancel_goal/_service_event"
GET_RESULT = "/fibonacci/_action/get_result/_service_event"
FEEDBACK = "/fibonacci/_action/feedback"
STATUS = "/fibonacci/_action/status"
TYPES = {SEND_GOAL: "test_msgs/action/Fibonacci_SendGoal_Event", CANCEL_GOAL: "action_msgs/srv/CancelGoal_Event",
         GET_RESULT: "test_msgs/action/Fibonacci_GetResult_Event",
         FEEDBACK: "test_msgs/action/Fibonacci_FeedbackMessage", STATUS: "action_msgs/msg/GoalStatusArray"}
EVENT_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
T0 = 1_700_000_000_000_000_000
REPO = Path(__file__).resolve().parents[1]


# --- names and selection ----------------------------------------------------------------------------------
@pytest.mark.parametrize(("topic", "type_name", "expected"), [
    (SEND_GOAL, TYPES[SEND_GOAL], True),
    (CANCEL_GOAL, TYPES[CANCEL_GOAL], True),
    (GET_RESULT, TYPES[GET_RESULT], True),
    (FEEDBACK, TYPES[FEEDBACK], True),
    (STATUS, TYPES[STATUS], True),
    ("/_action/status", TYPES[STATUS], False),  # no action name before the suffix
    ("/fibonacci/action/status", TYPES[STATUS], False),
    (STATUS, "action_msgs/msg/GoalStatus", False),
    (SEND_GOAL, "test_msgs/action/Fibonacci_SendGoal", False),
    (FEEDBACK, "std_msgs/msg/String", False),
])
def test_action_topics_are_recognised_by_name_and_type(topic: str, type_name: str, expected: bool) -> None:
    assert is_action_topic(topic, type_name) is expected


def test_action_names_types_and_topics_map_both_ways() -> None:
    assert {action_name(topic) for topic in TYPES} == {FIB}
    assert action_topics(FIB) == {"send_goal": SEND_GOAL, "cancel_goal": CANCEL_GOAL, "get_result": GET_RESULT,
                                  "feedback": FEEDBACK, "status": STATUS}
    assert [action_type(TYPES[topic]) for topic in TYPES] == ["test_msgs/action/Fibonacci", None,
                                                              "test_msgs/action/Fibonacci",
                                                              "test_msgs/action/Fibonacci", None]
    with pytest.raises(ValueError, match="is an action's topic, not an action name"):
        action_topics(STATUS)


ACTION = (SEND_GOAL, TYPES[SEND_GOAL])
CANCEL = (CANCEL_GOAL, TYPES[CANCEL_GOAL])
ACTION_FEEDBACK = (FEEDBACK, TYPES[FEEDBACK])
SERVICE = ("/set_flag/_service_event", "std_srvs/srv/SetBool_Event")


@pytest.mark.parametrize(("options", "topic", "expected"), [
    ({"actions": [FIB]}, ACTION, True),
    ({"actions": ["fibonacci"]}, CANCEL, True),
    ({"actions": [FIB]}, ACTION_FEEDBACK, True),
    ({"actions": ["/other"]}, ACTION, False),
    ({"all_actions": True}, CANCEL, True),
    ({"all_actions": True}, SERVICE, False),
    ({"all_actions": True, "exclude_actions": [FIB]}, ACTION_FEEDBACK, False),
    # the topic and service options never take an action's topics (CancelGoal_Event is a srv event type)
    ({"all_services": True}, CANCEL, False),
    ({"all_topics": True, "include_hidden_topics": True}, ACTION_FEEDBACK, False),
    ({"topics": [FEEDBACK]}, ACTION_FEEDBACK, False),
    # the regexes see the action's name
    ({"regex": "^/fibonacci$"}, ACTION, True),
    ({"regex": "_action"}, ACTION, False),
    ({"all_actions": True, "exclude_regex": "^/fib"}, ACTION, False),
])
def test_action_topics_are_selected_as_rosbag2_kilted_selects_them(options: dict[str, Any],
                                                                   topic: tuple[str, str], expected: bool) -> None:
    assert TopicFilter(RecordOptions(**options), set()).selects(*topic, publisher_count=1) is expected


# --- definitions ------------------------------------------------------------------------------------------
def test_generated_action_types_have_definitions_hashes_and_classes(tmp_path: Path) -> None:
    """The types rosidl generates for an action have no file of their own; their IDL is made here and must give
    rosidl's hash in rosbags, which decodes every message."""
    writer = BagWriter(tmp_path / "bag")
    for topic, type_name in TYPES.items():
        writer.add_topic(TopicInfo(topic, type_name))
        assert message_definition(type_name)[0] in ("ros2idl", "ros2msg")
        assert type_hash(type_name).startswith("RIHS01_")
    goal_event = Fibonacci.Impl.SendGoalService.Event()
    goal_event.info.event_type = ServiceEventInfo.REQUEST_RECEIVED
    goal_event.request = [Fibonacci.Impl.SendGoalService.Request(goal=Fibonacci.Goal(order=7))]
    feedback = message_class(TYPES[FEEDBACK])(feedback=Fibonacci.Feedback(sequence=[0, 1, 1]))
    writer.write(SEND_GOAL, serialize_message(goal_event), T0, T0)
    writer.write(FEEDBACK, serialize_message(feedback), T0 + 1, T0 + 1)
    writer.close()
    decoded = rosbags_messages(tmp_path / "bag")
    assert decoded[SEND_GOAL][0].request[0].goal.order == 7
    assert list(decoded[FEEDBACK][0].feedback.sequence) == [0, 1, 1]


# --- bad input --------------------------------------------------------------------------------------------
def test_an_action_topic_given_as_action_name_is_a_load_error(tmp_path: Path) -> None:
    with in_process_manager("bad_action_test") as manager:
        with pytest.raises(Exception, match=r"record\.actions.*'/fibonacci/_action/status' is an action's topic"):
            load_recorder(manager, tmp_path / "bag", **{"record.actions": [STATUS]})
        assert manager.context.ok()


# --- recording a real action ------------------------------------------------------------------------------
def load_recorder(manager: ComponentManager, uri: Path, **parameters: Any) -> Recorder:
    loaded = manager.load(load_request({"package": "components", "plugin": "components::Recorder",
                                        "name": "action_recorder",
                                        "parameters": {"storage.uri": str(uri), **parameters}}, 1))
    return loaded.node


class FibonacciProcess:
    """What another process would run: an introspected action server and client on ComponentNodes, and a plain
    rclpy action server (``/plain``, no introspection), spun by an executor of their own context. The server
    notes every goal it executes and every cancel request it gets; a goal of order 6 runs until canceled."""

    def __init__(self) -> None:
        self.executed: list[tuple[bytes, int]] = []
        self.cancel_requests: list[bytes] = []
        self.context = process_context()
        self.server_node = ComponentNode("fibonacci_server", context=self.context)
        self.client_node = ComponentNode("fibonacci_client", context=self.context)
        self.server = self.server_node.create_action_server(Fibonacci, FIB, self._execute,
                                                            goal_callback=self._accept,
                                                            cancel_callback=self._on_cancel)
        self.plain = ActionServer(self.server_node, Fibonacci, "/plain", self._execute)
        self.client = self.client_node.create_action_client(Fibonacci, FIB)
        self.plain_client = self.client_node.create_action_client(Fibonacci, "/plain")
        for endpoint, node in ((self.server, self.server_node), (self.client, self.client_node)):
            endpoint.configure_introspection(node.get_clock(), EVENT_QOS, ServiceIntrospectionState.CONTENTS)
        self.executor = MultiThreadedExecutor(context=self.context)
        self.executor.add_node(self.server_node)
        self.executor.add_node(self.client_node)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()

    @staticmethod
    def _accept(goal: Any) -> GoalResponse:
        return GoalResponse.ACCEPT if goal.order <= 10 else GoalResponse.REJECT

    def _on_cancel(self, goal_handle: Any) -> CancelResponse:
        self.cancel_requests.append(bytes(goal_handle.goal_id.uuid))
        return CancelResponse.ACCEPT

    def _execute(self, goal_handle: Any) -> Any:
        self.executed.append((bytes(goal_handle.goal_id.uuid), goal_handle.request.order))
        if goal_handle.request.order == 6:
            wait_until(lambda: goal_handle.is_cancel_requested, 20.0)
            goal_handle.canceled()
            return Fibonacci.Result()
        sequence = [0, 1]
        for _ in range(goal_handle.request.order - 1):
            sequence.append(sequence[-1] + sequence[-2])
            goal_handle.publish_feedback(Fibonacci.Feedback(sequence=sequence))
        goal_handle.succeed()
        return Fibonacci.Result(sequence=sequence)

    def close(self) -> None:
        self.executor.shutdown()
        self._thread.join(timeout=10.0)
        self.server_node.destroy_node()
        self.client_node.destroy_node()


def done(future: Any) -> Any:
    assert wait_until(future.done, 20.0), "no answer from the action server"
    return future.result()


def written(recorder: Recorder, topic: str) -> int:
    current = recorder.stats()["current"]
    return current["topics"].get(topic, {}).get("written", 0) if current else 0


@pytest.fixture()
def fibonacci() -> Iterator[FibonacciProcess]:
    process = FibonacciProcess()
    try:
        yield process
    finally:
        process.close()


def test_an_action_is_recorded_with_its_service_events_and_listed_by_bag_info(
        tmp_path: Path, fibonacci: FibonacciProcess, capfd: pytest.CaptureFixture[str]) -> None:
    with in_process_manager("action_recording_test") as manager:
        recorder = load_recorder(manager, tmp_path / "bag", **{"record.actions": [FIB, "/plain"]})
        graph = fibonacci.server_node
        # feedback is volatile: the recorder (and the client) must be subscribed before the first goal
        assert wait_until(lambda: all(graph.count_subscribers(t) >= (2 if t in (FEEDBACK, STATUS) else 1)
                                      for t in TYPES), 20.0), "the recorder did not subscribe every action topic"
        assert wait_until(lambda: graph.count_subscribers("/plain/_action/feedback") >= 2, 20.0)
        assert fibonacci.client.wait_for_server(timeout_sec=20.0)
        feedback: list[list[int]] = []
        accepted = done(fibonacci.client.send_goal_async(
            Fibonacci.Goal(order=5), feedback_callback=lambda m: feedback.append(list(m.feedback.sequence))))
        assert accepted.accepted
        result = done(accepted.get_result_async())
        assert list(result.result.sequence) == [0, 1, 1, 2, 3, 5]
        assert not done(fibonacci.client.send_goal_async(Fibonacci.Goal(order=20))).accepted  # rejected
        done(accepted.cancel_goal_async())  # too late: the goal has succeeded; still a cancel request and response
        assert fibonacci.plain_client.wait_for_server(timeout_sec=20.0)
        plain = done(fibonacci.plain_client.send_goal_async(Fibonacci.Goal(order=3)))
        done(plain.get_result_async())
        # 4 events per call: REQUEST_SENT, RESPONSE_RECEIVED by the client, REQUEST_RECEIVED, RESPONSE_SENT by the
        # server
        expected = {SEND_GOAL: 8, GET_RESULT: 4, CANCEL_GOAL: 4, FEEDBACK: 4}
        assert wait_until(lambda: all(written(recorder, t) >= n for t, n in expected.items())
                          and written(recorder, "/plain/_action/feedback") >= 2, 20.0), recorder.stats()
        recorder.stop_recording()
    warnings = capfd.readouterr().err  # rcutils logs to the process's stderr
    assert ("record.actions: action /plain recorded without its send_goal, cancel_goal, get_result topics "
            "(service events exist only where") in warnings, warnings
    assert "action /fibonacci recorded without" not in warnings

    decoded = rosbags_messages(tmp_path / "bag")
    assert {topic: len(decoded[topic]) for topic in expected} == expected
    goals = decoded[SEND_GOAL]
    kinds = sorted(event.info.event_type for event in goals)
    assert kinds == sorted([ServiceEventInfo.REQUEST_SENT, ServiceEventInfo.REQUEST_RECEIVED,
                            ServiceEventInfo.RESPONSE_SENT, ServiceEventInfo.RESPONSE_RECEIVED] * 2)
    requests = [e for e in goals if e.info.event_type == ServiceEventInfo.REQUEST_RECEIVED]
    assert sorted(e.request[0].goal.order for e in requests) == [5, 20]
    sent = {e.info.sequence_number: e.request[0].goal.order for e in goals
            if e.info.event_type == ServiceEventInfo.REQUEST_SENT}
    assert sent == {e.info.sequence_number: e.request[0].goal.order for e in requests}  # the same calls
    responses = [e.response[0].accepted for e in goals if e.info.event_type == ServiceEventInfo.RESPONSE_SENT]
    assert sorted(responses) == [False, True]
    results = [e.response[0] for e in decoded[GET_RESULT] if e.info.event_type == ServiceEventInfo.RESPONSE_SENT]
    assert [list(r.result.sequence) for r in results] == [[0, 1, 1, 2, 3, 5]]
    recorded = [list(m.feedback.sequence) for m in decoded[FEEDBACK]]
    assert recorded == [[0, 1, 1], [0, 1, 1, 2], [0, 1, 1, 2, 3], [0, 1, 1, 2, 3, 5]]  # every feedback published
    # rclpy's client drops feedback that arrives after the goal's result: what it got is the start of the bag's
    assert feedback and recorded[:len(feedback)] == feedback
    assert decoded[STATUS], "no status recorded"
    assert "/plain/_action/send_goal/_service_event" not in decoded  # no introspection there

    info = format_bag_info(tmp_path / "bag")
    assert "Actions:           2" in info
    assert "Action information:" in info
    assert (f"  Action: {FIB} | Type: test_msgs/action/Fibonacci | Topics: 2 | Service: 3 | "
            "Serialization Format: cdr") in info
    assert "    Service: send_goal | Event Count: 8" in info
    assert "    Topic: feedback | Count: 4" in info
    assert "  Action: /plain | Type: test_msgs/action/Fibonacci | Topics: 2 | Service: 3" in info
    assert "    Service: send_goal | Event Count: 0" in info
    assert "no service events (no action introspection where it ran)" in info
    assert "_action" not in info.split("Action information:")[0]  # not listed as topics or services


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ipc_component.cli", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=90)


def test_record_start_actions_records_another_processes_action(tmp_path: Path, fibonacci: FibonacciProcess) -> None:
    """``ipc-component record start --actions`` on a container process; the action server and client are in this
    process: the events cross a process boundary over DDS."""
    with ContainerProcess("--bag-root", str(tmp_path), name="/ax/container", cwd=REPO,
                          log_path=tmp_path / "container.log"):
        at = time.time() + 1.0
        started = cli("record", "start", "/ax/container", "--session", "act", "--at", str(at), "--actions", FIB,
                      "--no-local-only")
        assert started.returncode == 0, started.stdout + started.stderr
        assert wait_until(lambda: time.time() > at, 20.0)  # the recording window has begun
        graph = fibonacci.server_node
        assert wait_until(lambda: all(graph.count_subscribers(t) >= (2 if t in (FEEDBACK, STATUS) else 1)
                                      for t in TYPES), 60.0), "the recorder did not subscribe every action topic"
        assert fibonacci.client.wait_for_server(timeout_sec=20.0)
        accepted = done(fibonacci.client.send_goal_async(Fibonacci.Goal(order=5)))
        done(accepted.get_result_async())
        bag = tmp_path / "act" / f"{os.uname().nodename}_ax_container"
        # the events are transient_local: what the recorder has not taken yet it still gets before the stop
        stopped = cli("record", "stop", "--session", "act", "--in", "2")
        assert stopped.returncode == 0, stopped.stdout + stopped.stderr
    decoded = rosbags_messages(bag)
    assert {topic: len(decoded.get(topic, [])) for topic in (SEND_GOAL, GET_RESULT, FEEDBACK)} == \
        {SEND_GOAL: 4, GET_RESULT: 4, FEEDBACK: 4}
    assert not [topic for topic in decoded if "_action" not in topic]  # only the action was selected


# --- replaying goals --------------------------------------------------------------------------------------
def goal_event(kind: int, goal_id: bytes, order: int) -> Any:
    event = Fibonacci.Impl.SendGoalService.Event()
    event.info.event_type = kind
    request = Fibonacci.Impl.SendGoalService.Request(goal=Fibonacci.Goal(order=order))
    request.goal_id.uuid = list(goal_id)
    event.request = [request]
    return event


def test_the_player_sends_recorded_goals_to_the_running_action_server(tmp_path: Path,
                                                                     fibonacci: FibonacciProcess) -> None:
    """Goals with their recorded ids, only the server side's requests (the client's REQUEST_SENT twins and the
    responses are skipped), a cancel for the goal it names; the recorded feedback is not published."""
    first, second = bytes(range(16)), bytes(range(16, 32))
    writer = BagWriter(tmp_path / "bag")
    for topic in (SEND_GOAL, CANCEL_GOAL, FEEDBACK):
        writer.add_topic(TopicInfo(topic, TYPES[topic]))
    cancel = Fibonacci.Impl.CancelGoalService.Event()
    cancel.info.event_type = ServiceEventInfo.REQUEST_RECEIVED
    cancel_request = Fibonacci.Impl.CancelGoalService.Request()
    cancel_request.goal_info.goal_id.uuid = list(second)
    cancel.request = [cancel_request]
    feedback = message_class(TYPES[FEEDBACK])(feedback=Fibonacci.Feedback(sequence=[0, 1]))
    recorded = [(SEND_GOAL, goal_event(ServiceEventInfo.REQUEST_SENT, first, 4)),
                (SEND_GOAL, goal_event(ServiceEventInfo.REQUEST_RECEIVED, first, 4)),
                (SEND_GOAL, goal_event(ServiceEventInfo.RESPONSE_SENT, first, 4)),
                (FEEDBACK, feedback),
                (SEND_GOAL, goal_event(ServiceEventInfo.REQUEST_RECEIVED, second, 6)),
                (CANCEL_GOAL, cancel)]
    for i, (topic, message) in enumerate(recorded):
        writer.write(topic, serialize_message(message), T0 + i * 10_000_000, T0 + i * 10_000_000)
    writer.close()

    services = [f"{FIB}/_action/{service}" for service in ("send_goal", "cancel_goal", "get_result")]
    clients_before = {service: fibonacci.server_node.count_clients(service) for service in services}
    with in_process_manager("action_replay_test") as manager:
        player = manager.load(load_request({
            "package": "components", "plugin": "components::Player", "name": "action_player",
            "parameters": {"storage.uri": str(tmp_path / "bag"), "play.send_actions_as_client": True,
                           "play.start_paused": True}}, 1)).node
        assert FEEDBACK not in player.stats()["published"]
        # the player's action client must know the server before the first goal (else rosbag2 skips it too),
        # and the server the client: a request from a writer the server has not discovered yet is dropped
        replay_client = player._senders[SEND_GOAL]._replay.client
        assert wait_until(replay_client.server_is_ready, 20.0)
        assert wait_until(lambda: all(fibonacci.server_node.count_clients(service) > clients_before[service]
                                      for service in services), 20.0)
        player.resume()
        assert wait_until(lambda: len(fibonacci.executed) == 2 and fibonacci.cancel_requests, 20.0), \
            (fibonacci.executed, fibonacci.cancel_requests, player.stats())
        assert player.stats()["published"] == {SEND_GOAL: 2, CANCEL_GOAL: 1}
    assert sorted(fibonacci.executed) == [(first, 4), (second, 6)]
    assert fibonacci.cancel_requests == [second]


def test_an_unloaded_components_action_server_and_client_leave_the_graph(ros: None) -> None:
    """A ComponentNode destroyed (a component unloaded) takes its action server and client with it: rclpy's
    destroy_node leaves them alive (and their services on the graph), and on Kilted their rcl_action
    introspection publishers then served old goals' events to the next recorder."""
    component = ComponentNode("fib_component")
    component.create_action_server(Fibonacci, "/leaving", lambda handle: Fibonacci.Result())
    component.create_action_client(Fibonacci, "/leaving")
    probe = rclpy.create_node("fib_probe")
    try:
        def services() -> set[str]:
            return {name for name, _ in probe.get_service_names_and_types() if name.startswith("/leaving/_action/")}

        assert wait_until(lambda: len(services()) == 3, 20.0), services()
        component.destroy_node()
        assert wait_until(lambda: not services(), 20.0), f"still on the graph: {sorted(services())}"
    finally:
        probe.destroy_node()
