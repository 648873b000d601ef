"""Supervision: if ListNodes lists a component, it is running. Real container processes over Fast DDS.

Each test injects one of the faults that used to stop a container silently (a callback that raises, an unload
racing a running callback, a component that destroys its own node or calls sys.exit, a destroy_node that raises
or hangs, a publisher reusing one message object) and checks that the container says so, keeps the rest
running, and keeps its bounds. The test plugins live in tests/container_test_plugins.py.

Tests that leave their container running share one container per executor model (``shared``: a module-scoped
container, checked after every test to be alive with nothing loaded, stopped at the end of the module with exit
status 0); the ones that stop, signal or crash their container start their own. How long an unload or a
shutdown takes is not asserted here: the exit statuses and the messages say which bound was applied
(benchmarks measure the times).
"""
from __future__ import annotations

import os
import pathlib
import re
import signal
import time
from typing import Any, Iterator

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from component_container.component_executors import EXECUTOR_KINDS
from ipc_testing.held_participant import HELD, held_participant_library
from ipc_testing.process import signal_another_thread
from container_process import (Containers, Received, SharedContainer, listing, node_names, unload_all, wait_until,
                               written)

PLUGINS = "tests.container_test_plugins"
TALKER = "components::Talker"
IPC = {"use_intra_process_comms": True}
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
# What the container logs when a component fails or one of its threads dies.
SUPERVISOR_ERRORS = re.compile(r"\(id \d+\) failed: |Container thread '.*' died")
# Load/unload cycles of the 1080p60 camera: a fixed subset by default, the full count with `make sweep`
# (IPC_CYCLES overrides both).
CYCLES, SWEEP_CYCLES = 24, 200


@pytest.fixture(scope="module")
def shared_container(request: pytest.FixtureRequest, ros: None) -> Iterator[SharedContainer]:
    """One ``--allow-module-plugins`` container per executor model (``request.param``), for the whole module."""
    container = SharedContainer("--allow-module-plugins", "--executor", request.param,
                                name=f"supervision_{request.param}")
    yield container
    container.close()




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


def log_order(uri: pathlib.Path) -> list[tuple[str, Any]]:
    """(topic, message) of a finished bag in log-time order, decoded by rosbags."""
    with Reader(uri) as reader:
        return [(connection.topic, TYPESTORE.deserialize_cdr(raw, connection.msgtype))
                for connection, _, raw in reader.messages()]


# --- a callback that raises ---------------------------------------------------------------------------------
@pytest.mark.parametrize("shared_container", EXECUTOR_KINDS, indirect=True)
def test_a_raising_callback_unloads_only_its_component(shared: SharedContainer, probe: Node) -> None:
    client, mark, prefix = shared.client, shared.mark(), shared.process.name
    diagnostics = Diagnostics(probe)
    received = Received(probe, "/sup_raise_chatter")
    talker_id = talker(client, "sup_raise_chatter")
    raising = client.load(f"{PLUGINS}:RaisingComponent", "tests", parameters={"raise_after": 5})
    assert raising.success, raising
    assert wait_until(lambda: listing(client) == [(talker_id, "/talker")], 10.0), listing(client)
    assert still_publishing(received, probe), "the other component stopped with the failing one"

    def failure_reported() -> DiagnosticStatus | None:  # not the "running" status published before it raised
        status = diagnostics.find(f"{prefix}: /raising_component")
        return status if status is not None and status.level == DiagnosticStatus.ERROR else None

    failed = wait_until(failure_reported, 10.0, probe)
    assert failed is not None, diagnostics.latest
    assert "deliberate failure in RaisingComponent" in failed.message
    running = diagnostics.find(f"{prefix}: /talker")
    assert running is not None and running.level == DiagnosticStatus.OK
    container = diagnostics.find(f"{prefix}: container")
    assert container is not None and container.level == DiagnosticStatus.OK, container
    assert client.load(TALKER, name="second").success  # still serving its services
    unload_all(client)
    failure = re.compile(rf"Component /raising_component \(id {raising.unique_id}\) failed: RuntimeError: "
                         "deliberate failure")
    assert wait_until(lambda: failure.search(shared.output_since(mark)), 10.0), shared.output_since(mark)
    output = shared.output_since(mark)
    assert "Traceback" in output and "_tick" in output  # the traceback is in the log


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
    assert process.process.wait(timeout=60) == 1
    process.stop()
    assert "Shutting down (component /raising_component failed" in process.output, process.output
    messages = read_bag(uri)  # finalized: metadata.yaml written, readable by an independent reader
    assert len(messages["/sup_exit_chatter"]) >= 10


# --- unloading while callbacks run or deliver ----------------------------------------------------------------
@pytest.mark.parametrize("shared_container", ["single", "multi", "events"], indirect=True)
def test_unload_during_a_running_callback_keeps_the_others_running(shared: SharedContainer, probe: Node) -> None:
    client, mark = shared.client, shared.mark()
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
    assert client.unload(talker_id).success
    assert not SUPERVISOR_ERRORS.search(shared.output_since(mark)), shared.output_since(mark)


@pytest.mark.parametrize("cycles", [int(os.environ.get("IPC_CYCLES") or CYCLES),
                                    pytest.param(int(os.environ.get("IPC_CYCLES") or SWEEP_CYCLES),
                                                 marks=pytest.mark.sweep)])
@pytest.mark.parametrize("shared_container", ["single", "events"], indirect=True)
def test_load_unload_cycles_of_a_1080p60_camera_next_to_imu_and_recorder(shared: SharedContainer, probe: Node,
                                                                         tmp_path: pathlib.Path,
                                                                         cycles: int) -> None:
    """Load/unload cycles of a 1920x1080 60 Hz camera (its timer callback is often running, and its camera_info
    goes to the recorder inline) while an IMU at 200 Hz is recorded in the same container, all intra-process."""
    client, mark = shared.client, shared.mark()
    imu = client.load("components::ImuDriver", extra=IPC, parameters={"rate": 200.0})
    uri = tmp_path / "cycles_bag"
    recorder = client.load("components::Recorder", extra=IPC, parameters={
        "storage.uri": str(uri), "record.topics": ["/imu/imu", "/cam/camera_info"]})
    assert imu.success and recorder.success, (imu, recorder)
    for cycle in range(cycles):
        camera = client.load("components::CameraDriver", name="cam", extra=IPC,
                             parameters={"width": 1920, "height": 1080, "fps": 60.0})
        assert camera.success, (cycle, camera)
        time.sleep(0.02 if cycle % 2 else 0.06)  # lets the camera's timer run (the unload meets it or not)
        assert client.unload(camera.unique_id).success, cycle
    assert listing(client) == [(imu.unique_id, "/imu"), (recorder.unique_id, "/recorder")]
    # IMU messages received before the last camera_info may still be on their way to the writer when this is
    # read: 40 more written (0.2 s at 200 Hz) leave at least 10 behind the last camera_info in the bag
    after_cycles = written(probe, "/recorder", "/imu/imu")
    assert wait_until(lambda: written(probe, "/recorder", "/imu/imu") >= after_cycles + 40, 20.0), \
        "the IMU stopped publishing during the cycles"
    assert client.unload(recorder.unique_id).success
    assert client.unload(imu.unique_id).success
    order = log_order(uri)
    seqs = [int(m.orientation_covariance[1]) for topic, m in order if topic == "/imu/imu"]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "IMU messages missing from the bag"
    last_camera_info = max(i for i, (topic, _) in enumerate(order) if topic == "/cam/camera_info")
    assert sum(1 for topic, _ in order[last_camera_info:] if topic == "/imu/imu") >= 10, \
        "the IMU's recording did not go on after the last camera cycle"
    assert not SUPERVISOR_ERRORS.search(shared.output_since(mark)), shared.output_since(mark)


@pytest.mark.parametrize("shared_container", ["events"], indirect=True)
def test_events_refuses_a_component_it_cannot_run(shared: SharedContainer, probe: Node) -> None:
    client, mark = shared.client, shared.mark()
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
    assert client.unload(talker_id).success
    assert not SUPERVISOR_ERRORS.search(shared.output_since(mark)), shared.output_since(mark)


@pytest.mark.parametrize("executor", ["single", "events"])
def test_a_callback_that_never_returns_does_not_hold_the_exit(containers: Containers, probe: Node,
                                                              tmp_path: pathlib.Path, executor: str) -> None:
    """A component stuck in a 600 s callback at shutdown: the shutdown overran its 2 s bound, so the container
    exits by itself (long before the callback would return) with status 1 and says why."""
    process, client = containers.start("--allow-module-plugins", "--shutdown-timeout", "2", "--executor", executor)
    marker = tmp_path / "stuck"
    stuck = client.load(f"{PLUGINS}:BlockingComponent", "tests",
                        parameters={"block_seconds": 600.0, "marker": str(marker)})
    assert stuck.success, stuck
    assert wait_until(marker.exists, 10.0), "the blocking callback never ran"
    assert process.stop(signal.SIGTERM, timeout=60.0) == 1, process.output
    output = process.output
    assert "A component callback was still running after the shutdown" in output, output
    assert output.index("Shutting down (SIGTERM)") < output.index("A component callback was still running")


# --- the manager's own thread ------------------------------------------------------------------------------
@pytest.mark.parametrize("shared_container", ["single", "events"], indirect=True)
def test_manager_survives_a_self_destroyed_node_and_sys_exit(shared: SharedContainer, probe: Node) -> None:
    client = shared.client
    gone = client.load(f"{PLUGINS}:SelfDestroyingComponent", "tests")
    assert gone.success, gone
    # listed until its timer has destroyed its node: then it is no longer running, so it is not listed
    assert wait_until(lambda: listing(client) == [], 10.0), listing(client)
    exiting = client.load(f"{PLUGINS}:ExitingConstructor", "tests")
    assert not exiting.success and exiting.error_message == "Component constructor threw an exception: 3"
    assert wait_until(lambda: ("exiting_constructor", "/") not in node_names(probe), 5.0, probe)
    loaded = client.load(TALKER)
    assert loaded.success
    assert listing(client) == [(loaded.unique_id, "/talker")]
    assert client.unload(loaded.unique_id).success


# --- destroying a component ---------------------------------------------------------------------------------
@pytest.mark.parametrize("shared_container", ["single"], indirect=True)
def test_a_raising_destroy_node_still_destroys_the_node(shared: SharedContainer, probe: Node) -> None:
    client = shared.client
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


@pytest.mark.parametrize("executor", ["single", "events"])
def test_unload_and_shutdown_are_bounded_by_the_shutdown_timeout(containers: Containers, probe: Node,
                                                                 executor: str) -> None:
    """A destroy_node that never returns: the unload answers with the bound it applied, and so does the
    shutdown (exit status 1, after unloading the others); neither waits for the component."""
    process, client = containers.start("--allow-module-plugins", "--shutdown-timeout", "2", "--executor", executor)
    received = Received(probe, "/sup_bound_chatter")
    talker_id = talker(client, "sup_bound_chatter")
    hanging = client.load(f"{PLUGINS}:HangingDestructor", "tests")
    unloaded = client.unload(hanging.unique_id)
    assert not unloaded.success and "did not finish within 2.0 s" in unloaded.error_message, unloaded
    assert listing(client) == [(talker_id, "/talker")]
    assert still_publishing(received, probe)
    assert client.load(f"{PLUGINS}:HangingDestructor", "tests", name="hangs_at_exit").success
    assert process.stop(signal.SIGTERM, timeout=30.0) == 1, process.output  # 2 s bound + exit margin
    assert "Unloading /talker" in process.output


@pytest.mark.parametrize("taken_by", ["main thread", "another thread"])
def test_a_second_signal_forces_the_exit(containers: Containers, taken_by: str) -> None:
    """The second SIGTERM ends the container at once, whichever of its threads the signal is given to: the
    kernel may give a signal sent to the process to any thread that does not block it, but only the main thread
    runs Python's handlers (and it waits for the shutdown meanwhile)."""
    process, client = containers.start("--allow-module-plugins", "--shutdown-timeout", "60")
    assert client.load(f"{PLUGINS}:HangingDestructor", "tests").success
    process.process.send_signal(signal.SIGTERM)
    # the first signal's shutdown is inside the hanging destroy_node (and may wait up to 60 s for it)
    assert wait_until(lambda: "Unloading /hanging_destructor" in process.output, 20.0), process.output
    assert process.alive(), "the first signal should wait (up to 60 s) for the hanging component"
    if taken_by == "main thread":
        assert process.stop(signal.SIGTERM, timeout=30.0) == 1
    else:
        signal_another_thread(process.pid, signal.SIGTERM)
        assert wait_until(lambda: not process.alive(), 30.0), process.output
        assert process.process.returncode == 1
    assert "Second signal" in process.output
    assert "Shutdown did not finish" not in process.output  # the second signal ended it, not the 60 s bound


def test_a_participant_that_never_finishes_its_destruction_does_not_hold_the_exit(
        containers: Containers, probe: Node, tmp_path_factory: pytest.TempPathFactory) -> None:
    """Fast DDS's livelock as the container destroys its participant, the last step of its shutdown
    (ipc_testing.held_participant: it never returns, and holds the GIL, so no Python thread, timer or signal
    handler runs again): the container still exits with status 1, the shutdown's overrun status, after the
    Python stacks of where it was held; its components were unloaded before."""
    library = held_participant_library(tmp_path_factory.getbasetemp())
    process, client = containers.start("--shutdown-timeout", "2", env={"LD_PRELOAD": str(library)})
    talker(client, "sup_held_chatter")
    assert process.stop(signal.SIGTERM, timeout=30.0) == 1, process.output
    assert "Unloading /talker" in process.output
    assert HELD in process.output and "Timeout" in process.output and "in destroy_node" in process.output


# --- reused message objects ---------------------------------------------------------------------------------
@pytest.mark.parametrize("shared_container", ["single"], indirect=True)
def test_a_publisher_reusing_one_object_records_distinct_messages(shared: SharedContainer, probe: Node,
                                                                  tmp_path: pathlib.Path) -> None:
    client, mark = shared.client, shared.mark()
    uri = tmp_path / "reuse_bag"
    recorder = client.load("components::Recorder", extra=IPC, parameters={
        "storage.uri": str(uri), "record.topics": ["/reused"]})
    assert recorder.success, recorder
    assert client.load(f"{PLUGINS}:ReusingPublisher", "tests", extra=IPC,
                       parameters={"count": 100, "delay": 1.0}).success
    assert wait_until(lambda: written(probe, "/recorder", "/reused") >= 100, 20.0), "the burst was not recorded"
    unload_all(client)
    assert [m.data for m in read_bag(uri)["/reused"]] == [str(i) for i in range(100)]
    output = shared.output_since(mark)
    assert output.count("publishes a message object it published before") == 1, output
