"""Supervision: if ListNodes lists a component, it is running. Real container processes over Fast DDS.

Each test injects one of the faults that used to stop a container silently (a callback that raises, an unload
racing a running callback, a component that destroys its own node or calls sys.exit, a destroy_node that raises
or hangs, a publisher reusing one message object) and checks that the container says so, keeps the rest
running, and keeps its bounds. The test plugins live in tests/container_test_plugins.py.
"""
from __future__ import annotations

import pathlib
import re
import signal
import time
from typing import Any

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from component_container.component_executors import EXECUTOR_KINDS
from container_process import Containers, Received, listing, node_names, wait_until

PLUGINS = "tests.container_test_plugins"
TALKER = "components::Talker"
IPC = {"use_intra_process_comms": True}
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
# What the container logs when a component fails or one of its threads dies.
SUPERVISOR_ERRORS = re.compile(r"\(id \d+\) failed: |Container thread '.*' died")


def talker(client: Any, topic: str) -> int:
    loaded = client.load(TALKER, parameters={"rate": 20.0}, remaps=[f"chatter:={topic}"])
    assert loaded.success, loaded
    return loaded.unique_id


def still_publishing(received: Received, probe: Node, seconds: float = 3.0) -> bool:
    """New messages keep arriving (the component's executor thread is alive)."""
    before = len(received.messages)
    return bool(wait_until(lambda: len(received.messages) >= before + 3, seconds, probe))


def read_bag(uri: pathlib.Path) -> dict[str, list[Any]]:
    """Every message of a finished bag, decoded by rosbags, per topic in log-time order."""
    messages: dict[str, list[Any]] = {}
    with Reader(uri) as reader:
        for connection, _, raw in reader.messages():
            messages.setdefault(connection.topic, []).append(TYPESTORE.deserialize_cdr(raw, connection.msgtype))
    return messages


class Diagnostics:
    """The latest /diagnostics statuses by name."""

    def __init__(self, node: Node) -> None:
        self.latest: dict[str, DiagnosticStatus] = {}
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on_array, 10)

    def _on_array(self, array: DiagnosticArray) -> None:
        self.latest.update({status.name: status for status in array.status})

    def find(self, suffix: str) -> DiagnosticStatus | None:
        return next((s for name, s in self.latest.items() if name.endswith(suffix)), None)


# --- a callback that raises ---------------------------------------------------------------------------------
@pytest.mark.parametrize("executor", EXECUTOR_KINDS)
def test_a_raising_callback_unloads_only_its_component(containers: Containers, probe: Node, executor: str) -> None:
    diagnostics = Diagnostics(probe)
    process, client = containers.start("--allow-module-plugins", "--executor", executor)
    received = Received(probe, "/sup_raise_chatter")
    talker_id = talker(client, "sup_raise_chatter")
    raising = client.load(f"{PLUGINS}:RaisingComponent", "tests", parameters={"raise_after": 5})
    assert raising.success, raising
    assert wait_until(lambda: listing(client) == [(talker_id, "/talker")], 10.0), listing(client)
    assert still_publishing(received, probe), "the other component stopped with the failing one"

    def failure_reported() -> DiagnosticStatus | None:  # not the "running" status published before it raised
        status = diagnostics.find(": /raising_component")
        return status if status is not None and status.level == DiagnosticStatus.ERROR else None

    failed = wait_until(failure_reported, 5.0, probe)
    assert failed is not None, diagnostics.latest
    assert "deliberate failure in RaisingComponent" in failed.message
    running = diagnostics.find(": /talker")
    assert running is not None and running.level == DiagnosticStatus.OK
    container = diagnostics.find(": container")
    assert container is not None and container.level == DiagnosticStatus.OK, container
    assert client.load(TALKER, name="second").success  # still serving its services
    assert process.stop() == 0
    assert re.search(r"Component /raising_component \(id 2\) failed: RuntimeError: deliberate failure", process.output)
    assert "Traceback" in process.output and "_tick" in process.output  # the traceback is in the log


@pytest.mark.parametrize("executor", ["single", "events"])
def test_exit_policy_finalizes_bags_and_exits_1(containers: Containers, probe: Node,
                                                tmp_path: pathlib.Path, executor: str) -> None:
    process, client = containers.start("--allow-module-plugins", "--on-component-error", "exit",
                                       "--executor", executor)
    uri = tmp_path / "exit_policy_bag"
    recorder = client.load("components::Recorder", extra=IPC, parameters={
        "storage.uri": str(uri), "record.topics": ["/sup_exit_chatter"]})
    assert recorder.success, recorder
    talker(client, "sup_exit_chatter")
    assert client.load(f"{PLUGINS}:RaisingComponent", "tests", parameters={"raise_after": 40}).success
    assert process.process.wait(timeout=30) == 1
    process.stop()
    assert "Shutting down (component /raising_component failed" in process.output, process.output
    messages = read_bag(uri)  # finalized: metadata.yaml written, readable by an independent reader
    assert len(messages["/sup_exit_chatter"]) >= 10


# --- unloading while callbacks run or deliver ----------------------------------------------------------------
@pytest.mark.parametrize("executor", ["single", "multi", "events"])
def test_unload_during_a_running_callback_keeps_the_others_running(containers: Containers, probe: Node,
                                                                   executor: str) -> None:
    process, client = containers.start("--allow-module-plugins", "--executor", executor)
    received = Received(probe, "/sup_unload_chatter")
    talker_id = talker(client, "sup_unload_chatter")
    slow_output = Received(probe, "/slow_output")
    for _ in range(5):  # the slow callback runs 5 ms of every ~6: each unload meets it running
        slow = client.load(f"{PLUGINS}:SlowPublisher", "tests")
        assert slow.success, slow
        assert wait_until(lambda: slow_output.messages, 10.0, probe)
        slow_output.messages.clear()
        unloaded = client.unload(slow.unique_id)
        assert unloaded.success, unloaded
    assert listing(client) == [(talker_id, "/talker")]
    assert still_publishing(received, probe), "unloading a component stopped the others"
    assert process.stop() == 0
    assert not SUPERVISOR_ERRORS.search(process.output), process.output


@pytest.mark.parametrize("executor", ["single", "events"])
def test_load_unload_cycles_of_a_1080p60_camera_next_to_imu_and_recorder(containers: Containers, probe: Node,
                                                                         tmp_path: pathlib.Path,
                                                                         executor: str) -> None:
    """200 load/unload cycles of a 1920x1080 60 Hz camera (its timer callback is often running, and its
    camera_info goes to the recorder inline) while an IMU at 200 Hz is recorded in the same container."""
    process, client = containers.start("--use-intra-process-comms", "--executor", executor)
    imu = client.load("components::ImuDriver", parameters={"rate": 200.0})
    uri = tmp_path / "cycles_bag"
    recorder = client.load("components::Recorder", parameters={
        "storage.uri": str(uri), "record.topics": ["/imu/imu", "/cam/camera_info"]})
    assert imu.success and recorder.success, (imu, recorder)
    for cycle in range(200):
        camera = client.load("components::CameraDriver", name="cam",
                             parameters={"width": 1920, "height": 1080, "fps": 60.0})
        assert camera.success, (cycle, camera)
        time.sleep(0.02 if cycle % 2 else 0.06)
        assert client.unload(camera.unique_id).success, cycle
    assert listing(client) == [(imu.unique_id, "/imu"), (recorder.unique_id, "/recorder")]
    end = time.time()
    assert client.unload(recorder.unique_id).success
    messages = read_bag(uri)
    seqs = [int(m.orientation_covariance[1]) for m in messages["/imu/imu"]]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "IMU messages missing from the bag"
    last = messages["/imu/imu"][-1].header.stamp
    assert end - (last.sec + last.nanosec * 1e-9) < 2.0, "the IMU stopped publishing during the cycles"
    assert messages["/cam/camera_info"], "no camera_info recorded"
    assert process.stop() == 0
    assert not SUPERVISOR_ERRORS.search(process.output), process.output


def test_events_refuses_a_component_it_cannot_run(containers: Containers, probe: Node) -> None:
    process, client = containers.start("--allow-module-plugins", "--executor", "events")
    guarded = client.load(f"{PLUGINS}:GuardedComponent", "tests")
    assert not guarded.success
    assert guarded.error_message == (
        "Component could not be started: /guarded_component has guard conditions, which rclpy's EventsExecutor "
        "cannot run; load it into a container with --executor single, multi or isolated"), guarded.error_message
    assert wait_until(lambda: ("guarded_component", "/") not in node_names(probe), 5.0, probe)
    received = Received(probe, "/sup_guard_chatter")
    talker_id = talker(client, "sup_guard_chatter")
    assert listing(client) == [(talker_id, "/talker")]
    assert still_publishing(received, probe)
    assert process.stop() == 0
    assert not SUPERVISOR_ERRORS.search(process.output), process.output


@pytest.mark.parametrize("executor", ["single", "events"])
def test_a_callback_that_never_returns_does_not_hold_the_exit(containers: Containers, probe: Node,
                                                              tmp_path: pathlib.Path, executor: str) -> None:
    """A component stuck in a callback at shutdown: the shutdown overran, so the container exits within the
    bound with status 1 and says why."""
    process, client = containers.start("--allow-module-plugins", "--shutdown-timeout", "2", "--executor", executor)
    marker = tmp_path / "stuck"
    stuck = client.load(f"{PLUGINS}:BlockingComponent", "tests",
                        parameters={"block_seconds": 600.0, "marker": str(marker)})
    assert stuck.success, stuck
    assert wait_until(marker.exists, 10.0), "the blocking callback never ran"
    start = time.monotonic()
    assert process.stop(signal.SIGTERM, timeout=15.0) == 1, process.output
    assert time.monotonic() - start < 8.0
    assert "A component callback was still running after the shutdown" in process.output, process.output


# --- the manager's own thread ------------------------------------------------------------------------------
@pytest.mark.parametrize("executor", ["single", "events"])
def test_manager_survives_a_self_destroyed_node_and_sys_exit(containers: Containers, probe: Node,
                                                            executor: str) -> None:
    process, client = containers.start("--allow-module-plugins", "--executor", executor)
    gone = client.load(f"{PLUGINS}:SelfDestroyingComponent", "tests")
    assert gone.success, gone
    time.sleep(0.5)  # its timer has destroyed its node: it is no longer running, so it is not listed
    assert wait_until(lambda: listing(client) == [], 5.0)
    exiting = client.load(f"{PLUGINS}:ExitingConstructor", "tests")
    assert not exiting.success and exiting.error_message == "Component constructor threw an exception: 3"
    assert wait_until(lambda: ("exiting_constructor", "/") not in node_names(probe), 5.0, probe)
    assert client.load(TALKER).success
    assert [name for _, name in listing(client)] == ["/talker"]
    assert process.stop() == 0


# --- destroying a component ---------------------------------------------------------------------------------
def test_a_raising_destroy_node_still_destroys_the_node(containers: Containers, probe: Node) -> None:
    process, client = containers.start("--allow-module-plugins")
    bad = client.load(f"{PLUGINS}:BadDestructor", "tests")
    assert bad.success, bad
    assert wait_until(lambda: ("bad_destructor", "/") in node_names(probe), 10.0, probe)
    unloaded = client.unload(bad.unique_id)
    assert not unloaded.success
    assert "destroy_node raised RuntimeError: deliberate failure" in unloaded.error_message, unloaded
    assert listing(client) == []
    assert wait_until(lambda: ("bad_destructor", "/") not in node_names(probe), 10.0, probe), \
        "the component's node lingers in the graph"
    assert wait_until(lambda: not probe.get_publishers_info_by_topic("/bad_destructor_output"), 10.0, probe)
    assert process.stop() == 0


@pytest.mark.parametrize("executor", ["single", "events"])
def test_unload_and_shutdown_are_bounded_by_the_shutdown_timeout(containers: Containers, probe: Node,
                                                                 executor: str) -> None:
    process, client = containers.start("--allow-module-plugins", "--shutdown-timeout", "2", "--executor", executor)
    received = Received(probe, "/sup_bound_chatter")
    talker_id = talker(client, "sup_bound_chatter")
    hanging = client.load(f"{PLUGINS}:HangingDestructor", "tests")
    start = time.monotonic()
    unloaded = client.unload(hanging.unique_id)
    assert time.monotonic() - start < 6.0
    assert not unloaded.success and "did not finish within 2.0 s" in unloaded.error_message, unloaded
    assert listing(client) == [(talker_id, "/talker")]
    assert still_publishing(received, probe)
    assert client.load(f"{PLUGINS}:HangingDestructor", "tests", name="hangs_at_exit").success
    start = time.monotonic()
    assert process.stop(signal.SIGTERM, timeout=15.0) == 1, process.output  # 2 s bound + exit margin
    assert time.monotonic() - start < 8.0
    assert "Unloading /talker" in process.output


def test_a_second_signal_forces_the_exit(containers: Containers) -> None:
    process, client = containers.start("--allow-module-plugins", "--shutdown-timeout", "60")
    assert client.load(f"{PLUGINS}:HangingDestructor", "tests").success
    process.process.send_signal(signal.SIGTERM)
    time.sleep(1.5)
    assert process.alive(), "the first signal should wait (up to 60 s) for the hanging component"
    start = time.monotonic()
    assert process.stop(signal.SIGTERM, timeout=10.0) == 1
    assert time.monotonic() - start < 5.0
    assert "Second signal" in process.output


# --- reused message objects ---------------------------------------------------------------------------------
def test_a_publisher_reusing_one_object_records_distinct_messages(containers: Containers,
                                                                  tmp_path: pathlib.Path) -> None:
    process, client = containers.start("--allow-module-plugins", "--use-intra-process-comms")
    uri = tmp_path / "reuse_bag"
    recorder = client.load("components::Recorder", parameters={
        "storage.uri": str(uri), "record.topics": ["/reused"]})
    assert recorder.success, recorder
    assert client.load(f"{PLUGINS}:ReusingPublisher", "tests", parameters={"count": 100, "delay": 1.0}).success
    time.sleep(2.5)
    assert client.unload(recorder.unique_id).success
    assert [m.data for m in read_bag(uri)["/reused"]] == [str(i) for i in range(100)]
    assert process.stop() == 0
    assert process.output.count("publishes a message object it published before") == 1, process.output
