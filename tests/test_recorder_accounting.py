"""Every message accounted for around a bag's edges: stop, unload, a slow writer, a window's end, the last
second's loss events, and a split read live.

A bag's counts must say what it holds: each message the recorder counts as received is in the bag or counted
as dropped with a reason, and one offered after the bag's cut point (the close of its cache) is not counted.

In-process: a container's manager with drivers and a recorder delivering intra-process, driven from the test;
bags are read back with rosbags. DDS messages come from a plain rclpy node in a context of its own.
"""
from __future__ import annotations

import threading
import time
import types
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rosbag2_interfaces.msg import MessagesLostEvent
from rosbags.rosbag2 import Reader
from std_msgs.msg import String
from std_srvs.srv import Trigger

from baglib.format.cdr_fast import CdrData
from baglib.format.metadata import TopicInfo
from baglib.write.writer import BagWriter
from component_container.component_manager import ComponentManager
from component_container.component_node import ComponentNode
from component_container.startup_file import load_request
from components.recorder import recording_session
from components.recorder.message_cache import CachedMessage, MessageCache, payload_size
from components.recorder.recorder import Recorder
from ipc_testing import in_process_manager, wait_until
from ipc_testing.process_context import process_context
from ipc_testing.s3_server import S3Server
from upload_harness import bucket, s3, stored, unloaded_work  # noqa: F401 - fixtures

IMU = "/imu/imu"
CAMERA = "/camera/image_raw"


@pytest.fixture(params=[2.0])
def manager(request: pytest.FixtureRequest) -> Iterator[ComponentManager]:
    """An in-process container; its shutdown timeout (the recorder's bound on finishing a bag) is the param."""
    SlowBagWriter.DISK_UP.set()
    try:
        with in_process_manager("accounting_test", use_intra_process_comms=True, allow_module_plugins=True,
                                shutdown_timeout=request.param) as manager:
            yield manager
    finally:
        SlowBagWriter.DISK_UP.set()  # a writer left waiting on it finishes


def load(manager: ComponentManager, plugin: str, package: str = "components", **parameters: Any) -> Any:
    return manager.load(load_request({"package": package, "plugin": plugin, "parameters": parameters}, 1))


def bag_counts(bag: Path) -> dict[str, int]:
    """Messages per topic, as rosbags reads them."""
    counts: dict[str, int] = {}
    with Reader(bag) as reader:
        for connection, _, _ in reader.messages():
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
    return counts


def accounted(stats: dict[str, Any], topic: str) -> bool:
    counts = stats["topics"][topic]
    return counts["received"] == counts["written"] + counts["dropped"]


# --- the cut point ------------------------------------------------------------------------------------------
def test_a_message_offered_after_the_close_is_not_counted_unless_the_recording_failed() -> None:
    stopped = MessageCache(1000)
    assert stopped.push(CachedMessage("/t", b"", 10, 1, 1)) is True
    stopped.close()
    assert stopped.push(CachedMessage("/t", b"", 10, 2, 2)) is None
    assert stopped.counts() == ({"/t": 1}, {}, {})
    failed = MessageCache(1000)
    failed.close(failed=True)
    assert failed.push(CachedMessage("/t", b"", 10, 1, 1)) is False
    assert failed.counts() == ({"/t": 1}, {}, {"/t": 1})


@pytest.fixture()
def slow_intake(monkeypatch: pytest.MonkeyPatch) -> None:
    """The intake pauses 2 ms between reading the current bag and offering to it, as a publisher's thread
    preempted there by a busy machine would."""
    def slow_size(payload: Any) -> int:
        time.sleep(0.002)
        return payload_size(payload)

    monkeypatch.setattr(recording_session, "payload_size", slow_size)


@pytest.mark.parametrize("end", ["unload", "stop"])
def test_the_end_of_a_bag_drops_nothing_it_took_in(manager: ComponentManager, slow_intake: None, tmp_path: Path,
                                                   end: str) -> None:
    """IMU messages offered inline while the bag ends: each counted one is in the bag, and none is reported
    dropped (an unload waits for the inline intake; a stop's cut point leaves later ones out, uncounted)."""
    bag = tmp_path / "bag"
    imu = load(manager, "components::ImuDriver", rate=500.0)
    loaded = load(manager, "components::Recorder", **{"storage.uri": str(bag), "record.topics": [IMU]})
    recorder = loaded.node
    assert wait_until(lambda: recorder.stats()["current"]["topics"].get(IMU, {}).get("written", 0) >= 50, 20.0)
    if end == "unload":
        assert not manager.unload(loaded.unique_id).error
        final = recorder.stats()["finished"][-1]
    else:
        final = recorder.stop_recording()
    manager.unload(imu.unique_id)
    counts = final["topics"][IMU]
    assert counts["dropped"] == 0 and counts["received"] == counts["written"], final
    assert bag_counts(bag)[IMU] == counts["written"]


# --- a slow writer at the stop ------------------------------------------------------------------------------
class SlowBagWriter(BagWriter):
    """A bag on a slow disk: every write takes 2 ms; while :data:`DISK_UP` is clear, writes wait for it."""

    DISK_UP = threading.Event()

    def write(self, topic: str, data: CdrData, log_time_ns: int, publish_time_ns: int,
              split: bool | None = None) -> None:
        self.DISK_UP.wait()
        time.sleep(0.002)
        super().write(topic, data, log_time_ns, publish_time_ns, split)


class SlowRecorder(Recorder):
    writer_class = SlowBagWriter


@pytest.mark.parametrize("manager", [0.5], indirect=True)
def test_a_writer_given_up_on_at_the_stop_leaves_counts_that_match_the_bag(manager: ComponentManager,
                                                                          tmp_path: Path) -> None:
    """The stop gives up on a writer far behind (0.4 s): what was queued is dropped and counted, what the writer
    holds counts as given up too, until it writes it and closes the bag; the final counts then match the bag."""
    bag = tmp_path / "bag"
    imu = load(manager, "components::ImuDriver", rate=1000.0)
    loaded = load(manager, "test_recorder_accounting:SlowRecorder", "test_recorder_accounting",
                  **{"storage.uri": str(bag), "record.topics": [IMU]})
    recorder = loaded.node
    assert wait_until(lambda: recorder.stats()["current"]["backlog_bytes"] > 300 * 400, 20.0), recorder.stats()
    final = recorder.stop_recording()
    manager.unload(imu.unique_id)
    assert "did not finish" in final["error"] and accounted(final, IMU), final
    assert set(final["drop_reasons"][IMU]) == {"storage_failed"}, final

    def closed_with_its_counts() -> dict[str, Any] | None:  # closed by the writer, its counts taken again
        stats = recorder.stats()["finished"][-1]
        closed = (bag / "metadata.yaml").exists() and bag_counts(bag)[IMU] == stats["topics"][IMU]["written"]
        return stats if closed else None

    settled = wait_until(closed_with_its_counts, 20.0)
    assert settled, recorder.stats()["finished"][-1]
    counts = settled["topics"][IMU]
    assert accounted(settled, IMU) and counts["received"] == final["topics"][IMU]["received"], settled
    # what the writer held at the give-up is written later (none when the stop met it between two batches)
    assert bag_counts(bag)[IMU] == counts["written"] >= final["topics"][IMU]["written"], settled
    manager.unload(loaded.unique_id)


@pytest.mark.parametrize("manager", [0.5], indirect=True)
def test_a_bag_closed_late_after_its_recorder_was_unloaded_is_reported_uploaded_and_no_second_failure(
        manager: ComponentManager, s3: S3Server, bucket: str, tmp_path: Path,
        capfd: pytest.CaptureFixture[str]) -> None:
    """The unload gives up on a writer stuck on its disk; when the disk comes back, the writer closes the bag with
    its counts after the node is gone. The bag's closing event has no node left to publish it (rclpy refuses even
    the destroyed node's name), which is no failure of the bag; the finalized bag still goes to the store whole,
    ``metadata.yaml`` with it. Until then the container's /diagnostics list the unloaded recorder's work left."""
    bag = tmp_path / "bag"
    imu = load(manager, "components::ImuDriver", rate=1000.0)
    loaded = load(manager, "test_recorder_accounting:SlowRecorder", "test_recorder_accounting",
                  **{"storage.uri": str(bag), "record.topics": [IMU], "upload.uri": f"s3://{bucket}/robot",
                     "upload.endpoint_url": s3.endpoint_url})
    recorder = loaded.node
    assert wait_until(lambda: recorder.stats()["current"]["topics"].get(IMU, {}).get("written", 0) >= 10, 20.0)
    SlowBagWriter.DISK_UP.clear()
    assert wait_until(lambda: recorder.stats()["current"]["backlog_bytes"] > 0, 20.0), recorder.stats()
    manager.unload(imu.unique_id)
    manager.unload(loaded.unique_id)
    assert "did not finish" in recorder.stats()["finished"][-1]["error"]
    left = unloaded_work(manager)  # the container tells, as long as the bag is not finalized
    assert len(left) == 1 and "not finalized" in left[0].message and \
        {value.key: value.value for value in left[0].values}["bags not finalized"] == str(bag), left
    SlowBagWriter.DISK_UP.set()
    output: list[str] = []  # the container's log, on stdout and stderr
    assert wait_until(lambda: output.extend(capfd.readouterr()) or "finished after all" in "".join(output), 20.0), \
        "".join(output)
    assert "after the failure" not in "".join(output), "".join(output)
    final = recorder.stats()["finished"][-1]
    assert "did not finish" in final["error"] and bag_counts(bag)[IMU] == final["topics"][IMU]["written"], final
    local = {f"robot/bag/{path.name}": path.read_bytes() for path in bag.iterdir()}
    assert "robot/bag/metadata.yaml" in local, sorted(local)
    assert wait_until(lambda: stored(s3, bucket) == local, 30.0), (sorted(stored(s3, bucket)), sorted(local))
    assert wait_until(lambda: not unloaded_work(manager), 20.0), unloaded_work(manager)


# --- events/messages_lost -----------------------------------------------------------------------------------
class Listener:
    """A plain node (not the container's: over DDS) collecting events/messages_lost."""

    def __init__(self) -> None:
        self.context = process_context()
        self.node = Node("loss_listener", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.events: list[MessagesLostEvent] = []
        self.node.create_subscription(MessagesLostEvent, "/events/messages_lost", self.events.append, 100)

    def wait(self, predicate: Callable[[], Any], timeout: float) -> Any:
        """Spin until ``predicate`` holds or ``timeout`` passes; its last value."""
        return wait_until(lambda: self.executor.spin_once(timeout_sec=0.02) or predicate(), timeout, interval=0)

    def trigger(self, service: str) -> Trigger.Response:
        client = self.node.create_client(Trigger, service)
        try:
            assert client.wait_for_service(timeout_sec=10.0), service
            future = client.call_async(Trigger.Request())
            assert self.wait(future.done, 20.0), f"no reply from {service}"
            return future.result()
        finally:
            self.node.destroy_client(client)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.fixture()
def listener() -> Iterator[Listener]:
    listener = Listener()
    try:
        yield listener
    finally:
        listener.close()


def reported(events: list[MessagesLostEvent], topic: str, field: str) -> int:
    return sum(getattr(stat, field) for event in events for stat in event.messages_lost_statistics
               if stat.topic_name == topic)


@pytest.mark.parametrize("manager", [0.5], indirect=True)
def test_the_losses_of_the_last_second_are_published_when_the_bag_closes(manager: ComponentManager,
                                                                         listener: Listener, tmp_path: Path) -> None:
    events = listener.events
    loaded = load(manager, "test_recorder_accounting:SlowRecorder", "test_recorder_accounting", **{
        "storage.uri": str(tmp_path / "bag"), "storage.max_cache_size": 1024 * 1024, "storage.stall_reserve": 0,
        "record.topics": [CAMERA]})
    recorder = loaded.node
    SlowBagWriter.DISK_UP.clear()  # the cache fills and frames are dropped, continuously
    camera = load(manager, "components::CameraDriver", width=320, height=240, fps=30.0)
    assert listener.wait(lambda: reported(events, CAMERA, "messages_lost_in_recorder") > 0, 15.0)
    final = recorder.stop_recording()  # frames were dropped since the last event, up to this instant
    dropped = sum(final["drop_reasons"][CAMERA].values())
    assert listener.wait(lambda: reported(events, CAMERA, "messages_lost_in_recorder") == dropped, 10.0), \
        (reported(events, CAMERA, "messages_lost_in_recorder"), final["drop_reasons"])
    SlowBagWriter.DISK_UP.set()
    manager.unload(camera.unique_id)
    manager.unload(loaded.unique_id)


def test_the_loss_events_of_a_new_bag_start_from_zero(manager: ComponentManager, listener: Listener,
                                                      tmp_path: Path) -> None:
    """DDS losses (what the subscription's message-lost event reports, fed here as the middleware would) of one
    bag are not reported again in the next one."""
    events = listener.events
    loaded = load(manager, "components::Recorder", **{"storage.uri": str(tmp_path / "bag"),
                                                      "record.topics": ["/nobody"]})
    recorder = loaded.node

    def lost(count: int) -> None:  # rclpy's QoSMessageLostInfo, as the subscription's event hands it over
        recorder._loss_events.dds_lost("/nobody", types.SimpleNamespace(total_count_change=count))

    lost(5)
    assert listener.wait(lambda: reported(events, "/nobody", "messages_lost_in_transport") == 5, 10.0)
    assert listener.trigger("/recorder/stop_recording").success
    assert listener.trigger("/recorder/start_recording").success
    lost(2)
    assert listener.wait(lambda: len(events) >= 2, 10.0)
    assert [reported([event], "/nobody", "messages_lost_in_transport") for event in events] == [5, 2]
    manager.unload(loaded.unique_id)


# --- a window's end with a busy executor --------------------------------------------------------------------
class Hog(ComponentNode):
    """Keeps the container's (single-threaded) executor busy for ``seconds`` from the instant ``at``."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("hog", **kwargs)
        self._at = self.declare_parameter("at", 0.0).value
        self._seconds = self.declare_parameter("seconds", 0.0).value
        self._timer = self.create_timer(0.01, self._tick)

    def _tick(self) -> None:
        if self._at and time.time() >= self._at:
            self._at = 0.0
            time.sleep(self._seconds)  # nothing else runs on this executor meanwhile


def test_messages_received_inside_the_window_are_written_or_counted(manager: ComponentManager,
                                                                   tmp_path: Path) -> None:
    """The executor is busy from 0.4 s before the window's end until 0.3 s after the bag was finalized: the DDS
    messages received before the end and taken only then are counted as lost (``recording_stopped``), so that
    every message published well inside the window is in the bag or counted."""
    bag = tmp_path / "bag"
    stop_at = time.time() + 2.0
    loaded = load(manager, "components::Recorder", **{"storage.uri": str(bag), "record.topics": ["/chatter"],
                                                      "record.stop_at": stop_at})
    recorder = loaded.node
    load(manager, "test_recorder_accounting:Hog", "test_recorder_accounting", at=stop_at - 0.4, seconds=1.0)
    talker = Node("window_talker", context=process_context())
    publisher = talker.create_publisher(String, "/chatter", 100)
    published: list[float] = []
    try:
        assert wait_until(lambda: publisher.get_subscription_count() > 0, 10.0)
        start = time.time()
        while time.time() < stop_at + 0.5:  # 100 Hz: the reader's 100-deep history holds the busy second
            publisher.publish(String(data=str(len(published))))
            published.append(time.time())
            time.sleep(max(0.0, start + len(published) / 100 - time.time()))
    finally:
        talker.destroy_node()
    well_inside = sum(1 for t in published if t < stop_at - 0.02)

    def received() -> int:
        finished = recorder.stats()["finished"]
        return finished[-1]["topics"]["/chatter"]["received"] if finished else 0

    assert wait_until(lambda: received() >= well_inside, 10.0), (received(), well_inside)
    final = recorder.stats()["finished"][-1]
    counts = final["topics"]["/chatter"]
    assert accounted(final, "/chatter"), final
    assert final["drop_reasons"]["/chatter"] == {"recording_stopped": counts["dropped"]} and counts["dropped"] > 0
    assert bag_counts(bag)["/chatter"] == counts["written"]
    manager.unload(loaded.unique_id)


# --- a split read live --------------------------------------------------------------------------------------
def test_the_current_file_is_never_none_during_a_split(tmp_path: Path) -> None:
    """``~/get_stats`` reads it while the writer thread splits (a None broke its readers)."""
    info = TopicInfo("/t", "std_msgs/msg/String", "cdr", [])
    readings = {"all": 0, "none": 0}
    done = threading.Event()

    def watch(writer: BagWriter) -> None:
        while not done.is_set():
            readings["all"] += 1
            readings["none"] += writer.current_file is None

    with BagWriter(tmp_path / "bag") as writer:
        writer.add_topic(info)
        watcher = threading.Thread(target=watch, args=(writer,))
        watcher.start()
        try:
            for n in range(10):
                writer.write("/t", b"\x00\x01\x00\x00\x01\x00\x00\x00\x00", n + 1, n + 1)
                writer.split()
        finally:
            done.set()
            watcher.join()
    assert readings["all"] and not readings["none"], f"{readings['none']} of {readings['all']} readings were None"
