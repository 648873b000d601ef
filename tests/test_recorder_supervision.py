"""Issue #8, the recorder side: a listed recorder is a running recorder, whatever its messages, types or disk do.

* a message object that cannot be serialized is dropped and reported, and the recording goes on;
* a bug in the writer thread is a storage failure: reported, the bag finalized at once;
* a topic whose type cannot be used in the recorder's process is ignored, and discovery goes on;
* a hung disk cannot block an unload or a SIGTERM beyond the container's shutdown timeout;
* ``health()`` says what an operator needs.

Real container processes over Fast DDS (the fixtures of test_recorder), started with ``--allow-module-plugins``
for the helper components in container_test_plugins and ``--shutdown-timeout 2`` (so that a hung disk costs the
tests 1.6 s, not the default's 8); the container of this module also sees a broken installation of
``stereo_msgs`` first on its PYTHONPATH (a type name that resolves to no message class).
"""
from __future__ import annotations

import json
import re
import signal
import threading
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import String
from std_srvs.srv import Trigger
from stereo_msgs.msg import DisparityImage

from component_container.health import ERROR, OK, WARN
from ipc_testing.process_context import process_context
from container_test_plugins import CrashingBagWriter, CrashingWriterRecorder, HangingBagWriter, HangingDiskRecorder
from test_recorder import (  # noqa: F401 - probe and log_dir are fixtures
    IMU,
    NOT_INFRASTRUCTURE,
    REPO,
    Container,
    Recorder as LoadedRecorder,
    Rig,
    log_dir,
    probe,
    verify_bag,
    wait_until,
)

PLUGINS = "tests.container_test_plugins"
IMU_TOPIC = "/sup_imu/imu"
SHUTDOWN_TIMEOUT = 2.0  # --shutdown-timeout of this module's containers

BROKEN_STEREO_MSGS = '''"""stereo_msgs as a broken installation shows it: the type name resolves to no message class."""


def DisparityImage() -> None:
    """Not a message class."""
'''


@pytest.fixture(scope="module")
def supervised_module(log_dir: Path, probe: Node, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    shadow = tmp_path_factory.mktemp("broken_site")
    (shadow / "stereo_msgs" / "msg").mkdir(parents=True)
    (shadow / "stereo_msgs" / "__init__.py").write_text("")
    (shadow / "stereo_msgs" / "msg" / "__init__.py").write_text(BROKEN_STEREO_MSGS)
    container = Container("recorder_supervision", log_dir, "--allow-module-plugins", "--shutdown-timeout",
                          f"{SHUTDOWN_TIMEOUT:g}", env={"PYTHONPATH": str(shadow)})
    try:
        rig = Rig(container, probe)
        rig.load_driver("components::ImuDriver", "sup_imu", IMU)
    except BaseException:
        container.kill()
        raise
    try:
        yield rig
    finally:
        rig.cleanup()
        assert container.stop() == 0, container.output[-3000:]


@pytest.fixture()
def supervised(supervised_module: Rig) -> Iterator[Rig]:
    """After each test the container must still be alive with its IMU driver, and no recorder left."""
    yield supervised_module
    supervised_module.cleanup()
    assert supervised_module.container.alive(), supervised_module.container.output[-3000:]
    assert "/sup_imu" in supervised_module.listed()


# --- item 3: supervised writer ------------------------------------------------------------------------------
def test_unserializable_message_is_dropped_and_recording_goes_on(supervised: Rig, tmp_path: Path) -> None:
    uri, topic = tmp_path / "broken", "/broken_camera/image_raw"
    recorder = supervised.record("recorder_broken", uri, **{"record.topics": [topic, IMU_TOPIC]})
    supervised.load_driver(f"{PLUGINS}:BrokenImagePublisher", "broken_camera", {"count": 30, "broken": 10},
                           package="tests")
    try:
        assert wait_until(lambda: recorder.stats()["current"]["topics"].get(topic, {}).get("written") == 29, 15.0), \
            recorder.stats()
        imu_written = recorder.stats()["current"]["topics"][IMU_TOPIC]["written"]
        assert wait_until(lambda: recorder.stats()["current"]["topics"][IMU_TOPIC]["written"] > imu_written, 5.0)
        live = recorder.stats()["current"]
        assert live["error"] is None
        assert live["drop_reasons"] == {topic: {"serialize_failed": 1}}
        assert "4294967295" in live["serialize_errors"][topic]  # struct's complaint about the uint32 height

        stop = recorder.trigger("stop_recording")
        assert stop.success is False
        final = json.loads(stop.message)
        assert final["serialize_errors"] == live["serialize_errors"] and final["error"] is None
        assert final["topics"][topic] == {"received": 30, "written": 29, "dropped": 1, "queue_dropped": 0,
                                           "rate_limited": 0, "repeated": 0}
        bag = verify_bag(uri)
        assert bag.seqs(topic) == [n for n in range(30) if n != 10]
        assert len(bag.seqs(IMU_TOPIC)) == final["topics"][IMU_TOPIC]["written"] > 0
        log = supervised.container.output
        dropped_logs = re.findall(rf"\[recorder_broken\]: Dropped a message on {topic} that cannot be serialized", log)
        assert len(dropped_logs) == 1
        assert re.search(rf"  dropped by reason: {topic} serialize_failed 1", log)
        recorder.unload()
    finally:
        supervised.unload_driver("broken_camera")


@pytest.fixture()
def in_process() -> Iterator[tuple[Context, Node, MultiThreadedExecutor]]:
    """The test process's context, a talker node, and an executor spinning in a thread."""
    context = process_context()
    talker = Node("supervision_talker", context=context)
    executor = MultiThreadedExecutor(context=context)
    executor.add_node(talker)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        yield context, talker, executor
    finally:
        executor.shutdown()
        thread.join(5.0)
        talker.destroy_node()


def test_writer_bug_is_a_storage_failure_with_a_finalized_bag(
        in_process: tuple[Context, Node, MultiThreadedExecutor], tmp_path: Path) -> None:
    context, talker, executor = in_process
    uri, probe_topic = tmp_path / "crash", "/health_probe"
    recorder = CrashingWriterRecorder(context=context, parameter_overrides=[
        Parameter("storage.uri", value=str(uri)),
        Parameter("record.topics", value=[probe_topic, CrashingBagWriter.CRASH_TOPIC])])
    executor.add_node(recorder)
    try:
        publishers = {t: talker.create_publisher(String, t, 10) for t in (probe_topic, CrashingBagWriter.CRASH_TOPIC)}
        stop = talker.create_client(Trigger, "/recorder/stop_recording")

        def written() -> int:
            return recorder.stats()["current"]["topics"].get(probe_topic, {}).get("written", 0)

        def publish_until(predicate: Callable[[], Any], topic: str) -> Any:
            return wait_until(lambda: publishers[topic].publish(String(data="x")) or predicate(), 10.0, interval=0.05)

        assert publish_until(lambda: written() >= 5, probe_topic)
        assert recorder.health().level == OK
        assert publish_until(lambda: recorder.stats()["current"]["error"], CrashingBagWriter.CRASH_TOPIC)
        error = recorder.stats()["current"]["error"]
        assert error == f"unexpected RuntimeError: deliberate bug in the writer, on {CrashingBagWriter.CRASH_TOPIC}"
        health = recorder.health()
        assert (health.level, health.message) == (ERROR, f"recording stopped: {error}")
        # finalized at the failure (the writer thread closes it right after reporting the error), while the
        # recorder is still loaded
        assert wait_until(lambda: (uri / "metadata.yaml").exists(), 10.0)
        bag = verify_bag(uri)
        assert len(bag.topic(probe_topic)) >= 5
        assert stop.wait_for_service(timeout_sec=10.0)
        response = stop.call(Trigger.Request(), timeout_sec=10.0)
        assert response is not None and response.success is False
        assert json.loads(response.message)["error"] == error
    finally:
        executor.remove_node(recorder)
        recorder.destroy_node()


def test_health_reports_the_recording(in_process: tuple[Context, Node, MultiThreadedExecutor],
                                      tmp_path: Path) -> None:
    context, talker, executor = in_process
    uri, topic = tmp_path / "healthy", "/health_probe"
    recorder = HangingDiskRecorder(context=context, parameter_overrides=[
        Parameter("storage.uri", value=str(uri)), Parameter("record.topics", value=[topic]),
        Parameter("storage.max_cache_size", value=20_000), Parameter("storage.stall_reserve", value=0)])
    recorder.shutdown_timeout = 1.0  # as a container started with --shutdown-timeout 1 sets it
    executor.add_node(recorder)
    try:
        publisher = talker.create_publisher(String, topic, 10)

        def publish_until(predicate: Callable[[], Any]) -> Any:
            return wait_until(lambda: publisher.publish(String(data="x" * 1000)) or predicate(), 10.0)

        assert publish_until(lambda: recorder.stats()["current"]["topics"].get(topic, {}).get("written", 0) >= 3)
        first = recorder.health()
        assert (first.level, first.message) == (OK, "recording")
        assert first.values["bag"] == str(uri) and first.values["current file"] == str(uri / "healthy_0.mcap")
        assert int(first.values["written"]) >= 3 and int(first.values["received"]) >= int(first.values["written"])
        assert float(first.values["free disk (MB)"]) > 0 and float(first.values["write rate (MB/s)"]) >= 0
        # The disk hangs after HANG_AFTER messages: the cache fills up and drops.
        assert publish_until(lambda: recorder.stats()["current"]["drop_reasons"].get(topic, {}).get("cache_full"))
        dropping = recorder.health()
        assert dropping.level == WARN and re.fullmatch(r"\d+ messages dropped in the last [\d.]+ s", dropping.message)
        assert int(dropping.values["written"]) == HangingBagWriter.HANG_AFTER
        stopped = recorder.stop_recording()  # bounded by the shutdown timeout
        assert stopped is not None and "was not finalized" in stopped["error"]
        assert (recorder.health().level, recorder.health().message) == (WARN, "not recording")
    finally:
        executor.remove_node(recorder)
        recorder.destroy_node()


# --- item 4: discovery survives types it cannot use ---------------------------------------------------------
def test_unusable_type_is_ignored_and_discovery_goes_on(supervised: Rig, tmp_path: Path) -> None:
    shadowed = "/shadowed/disparity"
    publisher = supervised.probe.create_publisher(DisparityImage, shadowed, 10)
    try:
        uri = tmp_path / "typed"
        recorder = supervised.record("recorder_types", uri, **{"record.all_topics": True,
                                                               "record.exclude_regex": NOT_INFRASTRUCTURE})
        pattern = (rf"\[recorder_types\]: Not recording {shadowed}: type stereo_msgs/msg/DisparityImage cannot be "
                   r"recorded here \(AttributeError: .*_TYPE_SUPPORT")
        assert wait_until(lambda: re.search(pattern, supervised.container.output), 10.0), \
            supervised.container.output[-3000:]
        assert wait_until(lambda: recorder.stats()["current"]["topics"].get(IMU_TOPIC, {}).get("written"), 5.0)
        assert shadowed not in recorder.stats()["current"]["topics"]
        assert recorder.trigger("stop_recording").success
        assert recorder.trigger("start_recording").success
        assert wait_until(lambda: recorder.stats()["current"]["topics"].get(IMU_TOPIC, {}).get("written"), 5.0)
        recorder.unload()
        for bag in (verify_bag(uri), verify_bag(tmp_path / "typed_1")):
            assert IMU_TOPIC in bag.counts() and shadowed not in bag.counts()
    finally:
        supervised.probe.destroy_publisher(publisher)


# --- item 6: a hung disk cannot hold an unload or a shutdown ------------------------------------------------
def wait_until_hung(recorder: LoadedRecorder) -> None:
    """The writer has taken HANG_AFTER messages and hangs; ~/get_stats still answers while it does."""
    hung = HangingBagWriter.HANG_AFTER
    assert wait_until(lambda: recorder.stats()["current"]["topics"].get(IMU_TOPIC, {}).get("written") == hung, 10.0)
    received = recorder.stats()["current"]["topics"][IMU_TOPIC]["received"]
    assert wait_until(lambda: recorder.stats()["current"]["topics"][IMU_TOPIC]["received"] > received + 20, 5.0)
    assert recorder.stats()["current"]["topics"][IMU_TOPIC]["written"] == hung


def not_finalized(recorder_name: str, uri: Path) -> str:
    return (rf"\[{recorder_name}\]: Recording to {re.escape(str(uri))} stopped: the writer did not finish within "
            rf"{0.8 * SHUTDOWN_TIMEOUT:.1f} s \(a hung disk\?\): the bag was not finalized; it can be repaired")


def test_hung_disk_unload_is_bounded(supervised: Rig, tmp_path: Path) -> None:
    uri = tmp_path / "hung"
    recorder = supervised.record("recorder_hung", uri, plugin=("tests", f"{PLUGINS}:HangingDiskRecorder"),
                                 **{"record.topics": [IMU_TOPIC]})
    wait_until_hung(recorder)
    # The writer never returns (HangingBagWriter): an unload that is answered was not held by it, and the log
    # says the bound was 80 % of the container's shutdown timeout.
    recorder.unload()
    assert re.search(not_finalized("recorder_hung", uri), supervised.container.output)
    assert not (uri / "metadata.yaml").exists()
    assert "/recorder_hung" not in supervised.listed()

    healthy = supervised.record("recorder_after_hang", tmp_path / "after", **{"record.topics": [IMU_TOPIC]})
    assert wait_until(lambda: healthy.stats()["current"]["topics"].get(IMU_TOPIC, {}).get("written"), 5.0)
    healthy.unload()
    assert verify_bag(tmp_path / "after").counts()[IMU_TOPIC] > 0


def test_hung_disk_sigterm_is_bounded(probe: Node, log_dir: Path, tmp_path: Path) -> None:
    container = Container("recorder_hung_sigterm", log_dir, "--allow-module-plugins", "--shutdown-timeout",
                          f"{SHUTDOWN_TIMEOUT:g}")
    try:
        rig = Rig(container, probe)
        rig.load_driver("components::ImuDriver", "sup_imu", IMU)
        uri = tmp_path / "hung"
        wait_until_hung(rig.record("recorder_hung", uri, plugin=("tests", f"{PLUGINS}:HangingDiskRecorder"),
                                   **{"record.topics": [IMU_TOPIC]}))
        assert container.stop(signal.SIGTERM, timeout=SHUTDOWN_TIMEOUT + 10.0) == 0, container.output[-3000:]
    finally:
        container.kill()
    assert re.search(not_finalized("recorder_hung", uri), container.output)


def test_the_default_shutdown_timeout_is_the_documented_one() -> None:
    """The tests above run with --shutdown-timeout 2; a container started without it gives a recorder the
    default that docs/container.md documents (and so its writer 80 % of that)."""
    from component_container.__main__ import parse_arguments

    table = (REPO / "docs" / "container.md").read_text()
    documented = re.search(r"^\| `--shutdown-timeout SECONDS` \| `([\d.]+)` \|", table, re.MULTILINE)
    assert documented, "docs/container.md has no --shutdown-timeout row"
    assert parse_arguments(["component_container"]).shutdown_timeout == float(documented.group(1))
