"""Latched topics in every file (``record.repeat_transient_local``) and time-bounded snapshots
(``storage.max_cache_duration``), as rosbag2 Rolling has them (ros2/rosbag2#2385-#2391, #2289).

A plain rclpy node in a context of its own publishes ``/tf_static`` and a camera's ``camera_info`` once,
transient_local, before the recorder exists (the usual case: it gets them as a late joiner over Fast DDS); an
IMU driver in the in-process container is the steady topic. Every split file is then opened alone with rosbags:
each must hold both latched messages, byte for byte as published (their header stamps are the original ones),
stamped as rosbag2 stamps the copies (the receive and publish time of the previous file's last message).
"""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any, Iterator

import pytest
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader
from sensor_msgs.msg import CameraInfo
from tf2_msgs.msg import TFMessage

from component_container.component_manager import ComponentConstructionError
from component_container.startup_file import load_request
from components.recorder.message_cache import CachedMessage, MessageCache
from ipc_testing import in_process_manager, wait_until
from ipc_testing.process_context import process_context

TF_STATIC = "/tf_static"
CAMERA_INFO = "/latched_cam/camera_info"
IMU = "/imu/imu"
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


@contextlib.contextmanager
def latched_publications() -> Iterator[tuple[TFMessage, CameraInfo]]:
    """/tf_static and a camera_info, each published once, transient_local, by a plain rclpy node (not the
    container's: over DDS)."""
    node = Node("latched_publisher", context=process_context())
    try:
        transform = TransformStamped()
        transform.header.stamp.sec, transform.header.frame_id = 1234, "base_link"
        transform.child_frame_id = "camera_link"
        transform.transform.translation.x = 0.25
        transform.transform.rotation.w = 1.0
        tf = TFMessage(transforms=[transform])
        info = CameraInfo(width=640, height=480, distortion_model="plumb_bob", d=[0.1, 0.0, 0.0, 0.0, 0.0])
        info.header.stamp.sec, info.header.stamp.nanosec, info.header.frame_id = 1234, 5678, "camera_optical"
        node.create_publisher(TFMessage, TF_STATIC, LATCHED).publish(tf)
        node.create_publisher(CameraInfo, CAMERA_INFO, LATCHED).publish(info)
        yield tf, info
    finally:
        node.destroy_node()


def load(manager: Any, plugin: str, **parameters: Any) -> Any:
    return manager.load(load_request({"package": "components", "plugin": plugin, "parameters": parameters}, 1))


def read_file(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    """One storage file opened alone: per topic, (log time, CDR) of its messages."""
    messages: dict[str, list[tuple[int, bytes]]] = {}
    with Reader(path) as reader:
        for connection, timestamp, raw in reader.messages():
            messages.setdefault(connection.topic, []).append((timestamp, raw))
    return messages


@pytest.mark.parametrize("storage_id, repeat", [
    ("mcap", {"record.repeat_all_transient_local": True}),
    ("sqlite3", {"record.repeat_transient_local": [TF_STATIC, f"{CAMERA_INFO}=1"]}),
], ids=["mcap-all", "sqlite3-named"])
def test_every_split_file_holds_the_latched_messages(tmp_path: Path, storage_id: str,
                                                     repeat: dict[str, Any]) -> None:
    bag = tmp_path / "bag"
    with latched_publications() as (tf, info), \
            in_process_manager("repeat_split", use_intra_process_comms=True, allow_module_plugins=True) as manager:
        load(manager, "components::ImuDriver", rate=50.0)
        recorder = load(manager, "components::Recorder", **{
            "storage.uri": str(bag), "storage.storage_id": storage_id, "storage.max_bagfile_duration": 2,
            "record.topics": [TF_STATIC, CAMERA_INFO, IMU], **repeat}).node

        def received(topic: str) -> int:
            return recorder.stats()["current"]["topics"].get(topic, {}).get("received", 0)

        assert wait_until(lambda: received(TF_STATIC) and received(CAMERA_INFO), 20.0), recorder.stats()
        assert wait_until(lambda: len(recorder._session.writer.files) >= 4, 30.0)  # three whole splits
        final = recorder.stop_recording()

    files = sorted(bag.glob(f"bag_*.{'mcap' if storage_id == 'mcap' else 'db3'}"),
                   key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    assert len(files) >= 4, files
    previous: dict[str, list[tuple[int, bytes]]] | None = None
    for path in files:
        messages = read_file(path)
        for topic, published, msg_type in ((TF_STATIC, tf, TFMessage), (CAMERA_INFO, info, CameraInfo)):
            assert len(messages.get(topic, [])) == 1, f"{path.name} alone lacks {topic}: {sorted(messages)}"
            timestamp, raw = messages[topic][0]
            assert deserialize_message(raw, msg_type) == published, f"{topic} in {path.name} is not as published"
            if previous is not None:  # rosbag2's stamp for the copies: the previous file's last message
                last = max(t for stamps in previous.values() for t, _ in stamps)
                assert timestamp == last, (path.name, topic, timestamp, last)
                assert timestamp <= min(t for t, _ in messages[IMU]), "a copy after the file's own messages"
        previous = messages
    for topic in (TF_STATIC, CAMERA_INFO):  # copies are not receptions: received = written + dropped still
        counts = final["topics"][topic]
        assert counts["received"] == counts["written"] == 1, counts
        assert counts["repeated"] == len(files) - 1, counts
    assert final["topics"][IMU]["repeated"] == 0 and final["drop_reasons"] == {}


@pytest.mark.parametrize("storage_id", ["mcap", "sqlite3"])
def test_a_snapshot_holds_the_latched_messages_and_only_the_last_seconds(tmp_path: Path, storage_id: str) -> None:
    bag = tmp_path / "bag"
    duration = 1.0
    with latched_publications() as (tf, info), \
            in_process_manager("repeat_snapshot", use_intra_process_comms=True, allow_module_plugins=True) as manager:
        load(manager, "components::ImuDriver", rate=100.0)
        recorder = load(manager, "components::Recorder", **{
            "storage.uri": str(bag), "storage.storage_id": storage_id, "storage.snapshot_mode": True,
            "storage.max_cache_duration": duration, "record.topics": [TF_STATIC, CAMERA_INFO, IMU],
            "record.repeat_transient_local": [TF_STATIC, CAMERA_INFO]}).node

        def received(topic: str) -> int:
            return recorder.stats()["current"]["topics"].get(topic, {}).get("received", 0)

        # the latched messages came long before the ring's second: evicted from it, kept for the snapshot
        assert wait_until(lambda: received(TF_STATIC) and received(CAMERA_INFO), 20.0), recorder.stats()
        start = received(IMU)
        assert wait_until(lambda: received(IMU) >= start + 300, 30.0)
        assert recorder._session.snapshot() is None
        assert wait_until(lambda: recorder.stats()["current"]["topics"][IMU]["written"] > 0, 10.0)
        final = recorder.stop_recording()

    messages = read_file(next(bag.glob("bag_0.*")))
    imu_times = [t for t, _ in messages[IMU]]
    span = (max(imu_times) - min(imu_times)) / 1e9
    assert duration - 0.1 <= span <= duration, f"the ring held {span:.3f} s, not the last {duration} s"
    for topic, published, msg_type in ((TF_STATIC, tf, TFMessage), (CAMERA_INFO, info, CameraInfo)):
        assert len(messages.get(topic, [])) == 1, f"the snapshot lacks {topic}"
        timestamp, raw = messages[topic][0]
        assert deserialize_message(raw, msg_type) == published
        assert timestamp == min(imu_times), "a latched copy is not stamped with the snapshot's first message"
        assert final["topics"][topic]["repeated"] == 1 and final["topics"][topic]["written"] == 0
    assert final["drop_reasons"] == {}, "ring evictions reported as losses"


def ring_of(max_bytes: int, max_duration: float, count: int, period_ns: int) -> tuple[list[CachedMessage],
                                                                                     MessageCache]:
    """A snapshot ring fed ``count`` messages of 100 bytes, one every ``period_ns`` of receive time."""
    ring = MessageCache(max_bytes, ring=True, max_duration=max_duration)
    for n in range(count):
        assert ring.push(CachedMessage("/steady", b"x" * 100, 100, n * period_ns, n * period_ns)) is True
    return ring.drain(), ring


def test_max_cache_duration_bounds_the_ring_and_the_smaller_limit_wins() -> None:
    period = 10_000_000  # 100 Hz for 5 s
    held, ring = ring_of(10**9, 1.0, 500, period)
    assert (held[-1].log_time_ns - held[0].log_time_ns) == 1_000_000_000 and len(held) == 101
    assert ring.evicted["/steady"] == 399  # the ring working as asked: counted apart, never as dropped
    assert not ring.dropped
    held, _ = ring_of(2_500, 1.0, 500, period)  # 25 messages by size: a quarter second, well under 1 s
    assert len(held) == 25
    held, _ = ring_of(10**9, 0.0, 500, period)  # no time bound: the size alone
    assert len(held) == 500


@pytest.mark.parametrize("parameters, complaint", [
    ({"storage.max_cache_duration": -1.0}, "parameter 'storage.max_cache_duration' must be 0 (no time bound) or in"),
    ({"storage.max_cache_duration": "30s"}, "parameter 'storage.max_cache_duration' must be a number"),
    ({"record.repeat_all_transient_local": "yes"},
     "parameter 'record.repeat_all_transient_local' must be a boolean or a depth"),
    ({"record.repeat_all_transient_local": -1}, "parameter 'record.repeat_all_transient_local' must be 0 (off)"),
    ({"record.repeat_transient_local": ["/tf_static=0"]}, "parameter 'record.repeat_transient_local' ('/tf_static')"),
    ({"record.repeat_transient_local": ["/tf_static=many"]}, "the depth of '/tf_static=many' must be an integer"),
    ({"record.repeat_transient_local": ["=2"]}, "entries must be 'TOPIC' or 'TOPIC=DEPTH'"),
], ids=["negative-duration", "duration-string", "repeat-all-string", "repeat-all-negative", "depth-zero",
        "depth-word", "no-topic"])
def test_bad_values_are_load_errors_naming_the_parameter(tmp_path: Path, parameters: dict[str, Any],
                                                         complaint: str) -> None:
    with in_process_manager("repeat_bad", allow_module_plugins=True) as manager:
        with pytest.raises(ComponentConstructionError) as error:
            load(manager, "components::Recorder", **{"storage.uri": str(tmp_path / "bag"), **parameters})
        assert complaint in str(error.value), error.value
        assert not (tmp_path / "bag").exists()
