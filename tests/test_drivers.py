"""Tests of the simulated sensor drivers (components.camera_driver / lidar_driver / imu_driver).

Each DDS test runs a driver and a plain rclpy listener node in the test process's one rclpy context,
waits until the listener's subscriptions are matched, spins a SingleThreadedExecutor until enough has arrived
(a count, not a time), takes what is still in flight (reliable: until every published message arrived) and
checks what arrived. Rates and phases are checked with a fake clock of the rate loop; how evenly real timers
tick on a loaded machine is the benchmarks' business.
"""
from __future__ import annotations

import array
import collections
import math
import os
import statistics
import time
import types
from typing import Any, Callable

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, Image, Imu, PointCloud2, PointField
from std_msgs.msg import Header

from component_container.component_node import ComponentNode
from component_container.intra_process import IntraProcessManager
from components import imu_driver, sensor_driver
from components.frame_buffers import FRAME_SLOTS
from components.camera_driver import CameraDriver, camera_info_topic_for
from components.imu_driver import ImuDriver
from components.lidar_driver import POINT_DTYPE, LidarDriver
from ipc_testing.process_context import process_context, process_id

#: How long a spin may take before the test fails: a guard against hanging, not a claim about speed.
PATIENCE_S = 20.0


class Ros:
    """The process's context with an executor, a listener node and the nodes a test creates."""

    def __init__(self) -> None:
        self.context = process_context()
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes: list[Node] = []
        self.listener = self.add(Node("listener", context=self.context))
        self.subscriptions: list[Any] = []

    def add(self, node: Node) -> Node:
        self.nodes.append(node)
        return node

    def driver(self, cls: type, name: str, **params: Any) -> Any:
        overrides = [Parameter(key, value=value) for key, value in params.items()]
        return self.add(cls(name, context=self.context, parameter_overrides=overrides))

    def listen(self, msg_type: type, topic: str, reliable: bool = True) -> list[tuple[float, Any]]:
        """Subscribe the listener to ``topic``; returns the list the (receive time, message) pairs go to."""
        received: list[tuple[float, Any]] = []
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=1000,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT)
        subscription = self.listener.create_subscription(
            msg_type, topic, lambda msg: received.append((time.monotonic(), msg)), qos)
        self.subscriptions.append(subscription)
        return received

    def publishers_here(self, topic: str, timeout: float = 10.0) -> list[Any]:
        """The publishers of ``topic`` in the graph that are this process's (its participant's GUID holds the
        process id): a container an earlier test killed can stay in the graph with a driver of the same name
        until its lease ends."""
        here = os.getpid() & 0xFFFF
        deadline = time.monotonic() + timeout
        while not (infos := [info for info in self.listener.get_publishers_info_by_topic(topic)
                             if process_id(info) == here]):
            assert time.monotonic() < deadline, f"no publisher of this process on {topic} in the graph"
            time.sleep(0.02)
        return infos

    def wait_matched(self, timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while any(sub.get_publisher_count() < 1 for sub in self.subscriptions):
            assert time.monotonic() < deadline, "listener subscriptions never matched the driver's publishers"
            time.sleep(0.02)

    def spin(self, *drivers: Node, until: Callable[[], bool], drained: Callable[[], bool] | None = None) -> None:
        """Match, then spin listener and drivers until ``until()``; stop the drivers and spin the listener until
        ``drained()`` (what was published has arrived)."""
        self.wait_matched()
        self.executor.add_node(self.listener)
        for driver in drivers:
            self.executor.add_node(driver)
        deadline = time.monotonic() + PATIENCE_S
        while not until():
            assert time.monotonic() < deadline, "the drivers did not publish enough"
            self.executor.spin_once(timeout_sec=0.05)
        for driver in drivers:  # stop publishing, then take what is in flight
            self.executor.remove_node(driver)
        while drained is not None and not drained():
            assert time.monotonic() < deadline, "published messages never arrived"
            self.executor.spin_once(timeout_sec=0.02)

    def close(self) -> None:
        try:
            self.executor.shutdown()
        finally:
            for node in self.nodes:
                node.destroy_node()


@pytest.fixture
def ros():
    harness = Ros()
    try:
        yield harness
    finally:
        harness.close()


def topic_of(driver: Node, topic: str) -> str:
    return driver.resolve_topic_name(topic)


def stamp_ns_of(msg: Any) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def seq_from_data(msg: Any) -> int:
    return int.from_bytes(bytes(msg.data[:8]), "little")


def check_sequence_and_stamps(msgs: list[Any], seq_of: Callable[[Any], int]) -> None:
    assert len(msgs) >= 5, f"only {len(msgs)} messages received"
    seqs = [seq_of(m) for m in msgs]
    assert seqs == list(range(len(seqs))), f"sequence not 0, 1, 2 ... without gaps: {seqs[:20]} ..."
    stamps = [stamp_ns_of(m) for m in msgs]
    assert all(b > a for a, b in zip(stamps, stamps[1:])), "header.stamp not strictly increasing"
    # The rate itself is checked deterministically with a fake clock (test_rate_loop_catches_up_and_caps_bursts);
    # wall-clock rates of a shared CI machine are not asserted.


def check_published_count(driver: Any, received: int) -> None:
    assert driver.published_count == received, "reliable: every published message should arrive"


# ---------------------------------------------------------------------------------------------- camera
def test_camera_publishes_images_and_camera_info(ros):
    camera = ros.driver(CameraDriver, "cam", width=320, height=240, fps=30.0, frame_id="cam_optical")
    assert camera.rate == 30.0 and camera.width == 320 and camera.encoding == "rgb8"
    images = ros.listen(Image, topic_of(camera, "~/image_raw"))
    infos = ros.listen(CameraInfo, topic_of(camera, "~/camera_info"))
    ros.spin(camera, until=lambda: len(images) >= 10,
             drained=lambda: len(images) == len(infos) == camera.published_count)

    msgs = [m for _, m in images]
    check_sequence_and_stamps(msgs, seq_from_data)
    check_published_count(camera, len(msgs))
    for msg in msgs:
        assert (msg.width, msg.height, msg.encoding, msg.step) == (320, 240, "rgb8", 960)
        assert len(msg.data) == 960 * 240
        assert msg.header.frame_id == "cam_optical"
        assert msg.is_bigendian == 0
    for a, b in zip(msgs, msgs[1:]):
        assert bytes(a.data[8:]) != bytes(b.data[8:]), "consecutive frames have identical payload"

    info_msgs = [m for _, m in infos]
    assert len(info_msgs) == len(msgs)
    assert [stamp_ns_of(m) for m in info_msgs] == [stamp_ns_of(m) for m in msgs]
    info = info_msgs[0]
    assert (info.width, info.height, info.header.frame_id) == (320, 240, "cam_optical")
    assert info.distortion_model == "plumb_bob" and len(info.d) == 5
    assert info.k[0] > 0 and info.k[4] == info.k[0] and info.k[8] == 1.0
    assert info.k[2] == pytest.approx(159.5) and info.k[5] == pytest.approx(119.5)
    assert info.p[0] == info.k[0] and info.p[10] == 1.0


@pytest.mark.parametrize("encoding, width, height, bytes_per_pixel", [
    ("rgb8", 64, 48, 3), ("bgr8", 64, 48, 3), ("rgba8", 64, 48, 4), ("bgra8", 64, 48, 4),
    ("mono8", 64, 48, 1), ("mono16", 64, 48, 2), ("rgb16", 64, 48, 6), ("yuv422", 64, 48, 2),
    ("yuv422_yuy2", 64, 48, 2), ("bayer_rggb8", 64, 48, 1), ("bayer_grbg16", 64, 48, 2),
    ("32FC1", 64, 48, 4), ("16UC3", 64, 48, 6), ("8UC4", 63, 47, 4), ("64FC2", 10, 10, 16),
])
def test_camera_encodings(ros, encoding, width, height, bytes_per_pixel):
    camera = ros.driver(CameraDriver, "cam", encoding=encoding, width=width, height=height)
    msg = camera.make_image(7, 1_000_000_123)
    assert msg.encoding == encoding
    assert msg.step == width * bytes_per_pixel
    assert len(msg.data) == msg.step * height
    assert (msg.width, msg.height) == (width, height)
    assert seq_from_data(msg) == 7
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1, 123)


def test_camera_info_topic_is_sibling():
    assert camera_info_topic_for("~/image_raw") == "~/camera_info"
    assert camera_info_topic_for("/front/left/image_rect") == "/front/left/camera_info"
    assert camera_info_topic_for("image") == "camera_info"


def test_camera_frames_are_fresh_objects(ros):
    camera = ros.driver(CameraDriver, "cam", width=64, height=48)
    first = camera.make_image(0, 0)
    snapshot = bytes(first.data)
    second = camera.make_image(1, 0)
    assert second is not first and second.data is not first.data and second.header is not first.header
    assert bytes(first.data) == snapshot, "building a frame modified an earlier one"
    assert bytes(second.data[8:]) != snapshot[8:]
    info_a, info_b = camera.make_camera_info(0), camera.make_camera_info(0)
    assert info_a.k is not info_b.k and info_a.header is not info_b.header


@pytest.mark.parametrize("seed", [0, 1])
def test_frames_depend_on_their_sequence_number_only(ros, seed):
    """Frames built into reused buffers equal frames built into fresh ones, and no frame kept by someone changes
    while later ones are built (what a subscriber or the recorder's cache keeps is never written again)."""
    rng = np.random.default_rng(seed)
    print(f"seed {seed}")
    camera = ros.driver(CameraDriver, "cam", width=64, height=48)
    lidar = ros.driver(LidarDriver, "lidar", points_per_scan=1000)
    reference_camera = ros.driver(CameraDriver, "cam_ref", width=64, height=48)
    reference_lidar = ros.driver(LidarDriver, "lidar_ref", points_per_scan=1000)
    kept: list[tuple[Any, bytes]] = []
    references = []  # all kept, so the reference drivers fill a fresh buffer for every frame
    for sequence in range(60):
        for build, reference in ((camera.make_image, reference_camera.make_image),
                                 (lidar.make_cloud, reference_lidar.make_cloud)):
            msg = build(sequence, 0)
            references.append(reference(sequence, 0))
            assert bytes(msg.data) == bytes(references[-1].data), f"frame {sequence} differs"
            assert seq_from_data(msg) == sequence
            if rng.random() < 0.2:
                kept.append((msg, bytes(msg.data)))
    assert all(bytes(msg.data) == snapshot for msg, snapshot in kept), "a kept frame was written again"
    assert camera._frames.reused > 30 and lidar._scans.reused > 30, "buffers were never handed out again"
    assert reference_camera._frames.reused == reference_lidar._scans.reused == 0


def test_frames_kept_by_an_intra_process_subscriber_stay_intact(ros):
    """Through the container's intra-process path (the subscriber gets the very object published): frames a
    subscriber keeps are never written again, while the driver reuses the buffers of the frames it dropped."""
    manager = IntraProcessManager()
    camera = ros.add(CameraDriver("cam", context=ros.context, intra_process_manager=manager,
                                  parameter_overrides=[Parameter("fps", value=200.0),
                                                       Parameter("width", value=64), Parameter("height", value=48)]))
    consumer = ros.add(ComponentNode("consumer", context=ros.context, intra_process_manager=manager))
    kept: list[tuple[Image, bytes]] = []
    received: list[int] = []
    window: collections.deque[Image] = collections.deque(maxlen=2)  # held a while, like the recorder's cache

    def on_image(msg: Image) -> None:
        window.append(msg)
        received.append(seq_from_data(msg))
        if len(received) % 3 == 0:  # and every third frame kept for good
            kept.append((msg, bytes(msg.data)))

    consumer.create_subscription(Image, "/cam/image_raw", on_image, 100)
    # Frames are published by hand, each taken by the subscriber before the next (the camera's timer never runs):
    # the subscriber keeps up, as on an idle machine. On a loaded one the subscription's queue would hold frames
    # for a while, and the fresh buffers the driver then fills would be right, but not countable.
    ros.executor.add_node(consumer)
    deadline = time.monotonic() + PATIENCE_S
    while camera._frames.reused < 100 and len(received) < 1000:
        published = len(received) + 1
        camera.publish_frame()
        while len(received) < published:
            assert time.monotonic() < deadline, "the subscriber did not take the frame"
            ros.executor.spin_once(timeout_sec=0.05)
    assert received == list(range(len(received)))
    assert camera._frames.reused >= 100, "the driver never got a buffer back"
    assert len(kept) > 30
    # A buffer is filled again only for a slot whose last frame the subscriber kept (plus each slot's first):
    # neither the window nor the publisher's memory of its last messages (REUSE_WATCH) holds one for long.
    assert camera._frames.filled <= FRAME_SLOTS + len(kept) + 1, (camera._frames.filled, len(kept))
    reference = ros.driver(CameraDriver, "cam_ref", width=64, height=48)
    for msg, snapshot in kept:
        assert bytes(msg.data) == snapshot, f"frame {seq_from_data(msg)} changed after it was delivered"
        assert snapshot == bytes(reference.make_image(seq_from_data(msg), 0).data)


def test_destroyed_drivers_drop_their_frame_buffers(ros):
    """An unloaded driver's node lives until the garbage collector finds it; its frames must not."""
    camera = ros.driver(CameraDriver, "cam", width=64, height=48)
    lidar = ros.driver(LidarDriver, "lidar", points_per_scan=100)
    camera.make_image(0, 0)
    lidar.make_cloud(0, 0)
    for driver in (camera, lidar):
        ros.nodes.remove(driver)  # destroyed here, not by the harness
        driver.destroy_node()
    assert camera._frames._buffers == [None] * FRAME_SLOTS and lidar._scans._buffers == [None] * FRAME_SLOTS


# ---------------------------------------------------------------------------------------------- lidar
def test_lidar_publishes_point_clouds(ros):
    lidar = ros.driver(LidarDriver, "lidar", points_per_scan=4096, rings=16, rate=20.0)
    clouds = ros.listen(PointCloud2, topic_of(lidar, "~/points"))
    ros.spin(lidar, until=lambda: len(clouds) >= 6, drained=lambda: len(clouds) == lidar.published_count)

    msgs = [m for _, m in clouds]
    check_sequence_and_stamps(msgs, seq_from_data)
    check_published_count(lidar, len(msgs))
    expected_fields = [("x", 0, PointField.FLOAT32), ("y", 4, PointField.FLOAT32), ("z", 8, PointField.FLOAT32),
                       ("intensity", 12, PointField.FLOAT32), ("ring", 16, PointField.UINT16),
                       ("time", 20, PointField.FLOAT32)]
    for msg in msgs:
        assert [(f.name, f.offset, f.datatype) for f in msg.fields] == expected_fields
        assert all(f.count == 1 for f in msg.fields)
        assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, 4096, 24, 4096 * 24)
        assert len(msg.data) == msg.row_step * msg.height
        assert msg.is_dense and not msg.is_bigendian
        assert msg.header.frame_id == "lidar"
    points = np.frombuffer(bytes(msgs[1].data), dtype=POINT_DTYPE)
    assert np.array_equal(points["ring"], np.arange(4096) % 16)
    assert points["time"][0] == 0.0 and 0.0 <= points["time"].min() and points["time"].max() < 1 / 20.0
    assert np.all(np.diff(points["time"]) >= 0)
    xyz = np.stack([points["x"][1:], points["y"][1:], points["z"][1:]])
    assert np.isfinite(xyz).all()
    distance = np.linalg.norm(xyz, axis=0)
    assert 0.5 < distance.min() and distance.max() < 50.0
    for a, b in zip(msgs, msgs[1:]):
        assert bytes(a.data[8:]) != bytes(b.data[8:]), "consecutive scans have identical payload"


def test_lidar_large_scan(ros):
    lidar = ros.driver(LidarDriver, "lidar", points_per_scan=131072)
    msg = lidar.make_cloud(3, 0)
    assert msg.width == 131072 and len(msg.data) == 131072 * 24 and seq_from_data(msg) == 3
    points = np.frombuffer(bytes(msg.data), dtype=POINT_DTYPE)
    assert points["ring"].max() == 31


# ---------------------------------------------------------------------------------------------- imu
def test_imu_publishes_at_1khz(ros):
    imu = ros.driver(ImuDriver, "imu", rate=1000.0)
    received = ros.listen(Imu, topic_of(imu, "~/imu"))
    ros.spin(imu, until=lambda: len(received) >= 300, drained=lambda: len(received) == imu.published_count)

    msgs = [m for _, m in received]
    check_sequence_and_stamps(msgs, lambda m: int(m.orientation_covariance[1]))
    check_published_count(imu, len(msgs))
    for msg in msgs:
        assert msg.header.frame_id == "imu"
        assert msg.orientation_covariance[0] == -1.0
        assert (msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w) == (0, 0, 0, 1)
    accel_z = [m.linear_acceleration.z for m in msgs]
    assert statistics.mean(accel_z) == pytest.approx(9.80665, abs=0.01)
    assert len(set(accel_z)) > len(accel_z) // 2, "accelerometer noise does not vary"
    assert msgs[0].linear_acceleration_covariance[0] > 0 and msgs[0].angular_velocity_covariance[0] > 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_imu_assembled_messages_equal_constructed_ones(ros, seed):
    """make_imu's slot assembly builds exactly what the public constructors build (any stamp, sequence, frame)."""
    rng = np.random.default_rng(seed)
    print(f"seed {seed}")
    imu = ros.driver(ImuDriver, "imu", frame_id="f" * int(rng.integers(1, 9)))
    assert imu.assembly_matches() and imu.make_imu.__func__ is ImuDriver.make_imu, "fell back to the constructors"
    for _ in range(200):
        sequence = int(rng.integers(0, 2 ** 53))
        stamp_ns = int(rng.integers(0, 2 ** 31 * 10 ** 9))  # Time.sec is an int32
        assembled, constructed = imu.make_imu(sequence, stamp_ns), imu.construct_imu(sequence, stamp_ns)
        assert assembled == constructed
        assert serialize_message(assembled) == serialize_message(constructed)
        assert imu_driver._layout(assembled) == imu_driver._layout(constructed)
        assert assembled.orientation_covariance[1] == sequence and stamp_ns == stamp_ns_of(assembled)


def test_imu_falls_back_to_the_constructors_when_the_assembly_differs(ros, monkeypatch):
    """A message class laid out otherwise (a future rosidl) is noticed at load: the driver warns and builds with
    the constructors."""
    def assemble_without_orientation(self: ImuDriver, sequence: int, stamp_ns: int) -> Imu:
        msg = object.__new__(Imu)
        msg._header = Header(stamp=sensor_driver.stamp_from_ns(stamp_ns), frame_id=self.frame_id)
        return msg
    monkeypatch.setattr(ImuDriver, "make_imu", assemble_without_orientation)
    warnings: list[str] = []
    monkeypatch.setattr(ImuDriver, "get_logger", lambda self: types.SimpleNamespace(warning=warnings.append))
    imu = ros.driver(ImuDriver, "imu", rate=100.0)
    assert len(warnings) == 1 and "building each message with the constructors" in warnings[0]
    assert imu.make_imu == imu.construct_imu
    received = ros.listen(Imu, topic_of(imu, "~/imu"))
    ros.spin(imu, until=lambda: len(received) >= 10, drained=lambda: len(received) == imu.published_count)
    check_sequence_and_stamps([m for _, m in received], lambda m: int(m.orientation_covariance[1]))


def test_capture_time_follows_sim_time(ros):
    imu = ros.driver(ImuDriver, "imu")
    before = time.time_ns()
    assert before <= imu.capture_ns() <= time.time_ns()  # the system clock without sim time
    clock = imu.get_clock()
    clock._set_ros_time_is_active(True)
    clock.set_ros_time_override(rclpy.time.Time(seconds=42, clock_type=clock.clock_type))
    assert imu.capture_ns() == 42_000_000_000
    assert stamp_ns_of(imu.make_imu(0, imu.capture_ns())) == 42_000_000_000


def test_imu_default_rate(ros):
    imu = ros.driver(ImuDriver, "imu")
    received = ros.listen(Imu, topic_of(imu, "~/imu"))
    ros.spin(imu, until=lambda: len(received) >= 20, drained=lambda: len(received) == imu.published_count)
    check_sequence_and_stamps([m for _, m in received], lambda m: int(m.orientation_covariance[1]))


# ---------------------------------------------------------------------------------------------- shared
def test_defaults(ros):
    camera = ros.driver(CameraDriver, "cam")
    lidar = ros.driver(LidarDriver, "lidar")
    imu = ros.driver(ImuDriver, "imu")
    assert (camera.width, camera.height, camera.encoding, camera.rate) == (640, 480, "rgb8", 30.0)
    assert (camera.frame_id, camera.topic, camera.qos_name) == ("camera", "~/image_raw", "reliable")
    assert camera.get_parameter("fps").value == 30.0
    assert (lidar.points_per_scan, lidar.rings, lidar.rate) == (32768, 32, 10.0)
    assert (lidar.frame_id, lidar.topic, lidar.qos_name) == ("lidar", "~/points", "reliable")
    assert (imu.rate, imu.frame_id, imu.topic, imu.qos_name) == (200.0, "imu", "~/imu", "reliable")
    for driver in (camera, lidar, imu):
        assert driver.published_count == 0
        assert driver.qos_profile.reliability == ReliabilityPolicy.RELIABLE
        assert driver.qos_profile.history == HistoryPolicy.KEEP_LAST and driver.qos_profile.depth == 10


@pytest.mark.parametrize("cls, params, parameter", [
    (CameraDriver, {"fps": -5.0}, "fps"),
    (CameraDriver, {"fps": 0}, "fps"),
    (CameraDriver, {"width": 0}, "width"),
    (CameraDriver, {"height": -1}, "height"),
    (CameraDriver, {"width": 640.5}, "width"),
    (CameraDriver, {"encoding": "rgb9"}, "encoding"),
    (CameraDriver, {"encoding": "yuv422", "width": 641}, "width"),
    (CameraDriver, {"qos": "fast"}, "qos"),
    (CameraDriver, {"frame_id": ""}, "frame_id"),
    (CameraDriver, {"topic": "bad topic!"}, "topic"),
    (LidarDriver, {"points_per_scan": 0}, "points_per_scan"),
    (LidarDriver, {"rings": 0}, "rings"),
    (LidarDriver, {"rings": 64, "points_per_scan": 32}, "rings"),
    (LidarDriver, {"rate": -10.0}, "rate"),
    (LidarDriver, {"rate": float("nan")}, "rate"),
    (ImuDriver, {"rate": 0.0}, "rate"),
    (ImuDriver, {"rate": "fast"}, "rate"),
    (ImuDriver, {"qos": "best_effort_please"}, "qos"),
])
def test_invalid_parameters_raise_value_error(ros, cls, params, parameter):
    overrides = [Parameter(key, value=value) for key, value in params.items()]
    with pytest.raises(ValueError, match=f"'{parameter}'"):
        cls("bad", context=ros.context, parameter_overrides=overrides)


def test_failed_construction_leaves_no_node(ros):
    # Keep the exception (whose traceback references the half-built node) alive: the node must be destroyed
    # explicitly, not just when the garbage collector gets to it.
    with pytest.raises(ValueError, match="'encoding'") as excinfo:
        CameraDriver("broken_camera", context=ros.context, parameter_overrides=[Parameter("encoding", value="x")])
    ros.driver(ImuDriver, "healthy_imu")
    deadline = time.monotonic() + 10.0
    while "healthy_imu" not in (names := ros.listener.get_node_names()):
        assert time.monotonic() < deadline
        time.sleep(0.02)
    assert "broken_camera" not in names
    assert excinfo.value is not None


def test_sensor_data_qos_is_best_effort(ros):
    camera = ros.driver(CameraDriver, "cam", width=64, height=48, qos="sensor_data")
    lidar = ros.driver(LidarDriver, "lidar", points_per_scan=256, rings=8, qos="sensor_data")
    imu = ros.driver(ImuDriver, "imu", qos="sensor_data")
    images = ros.listen(Image, topic_of(camera, "~/image_raw"), reliable=False)
    for driver, topic in ((camera, "~/image_raw"), (camera, "~/camera_info"), (lidar, "~/points"), (imu, "~/imu")):
        assert driver.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
        infos = ros.publishers_here(topic_of(driver, topic))
        assert [i.qos_profile.reliability for i in infos] == [ReliabilityPolicy.BEST_EFFORT]
    ros.spin(camera, until=lambda: len(images) >= 5)  # best effort: nothing to drain
    assert len(images) >= 5


def test_reliable_qos_in_graph(ros):
    imu = ros.driver(ImuDriver, "imu")
    infos = ros.publishers_here(topic_of(imu, "~/imu"))
    assert [i.qos_profile.reliability for i in infos] == [ReliabilityPolicy.RELIABLE]


# ---------------------------------------------------------------------------------------------- rate loop
class FakeClock:
    """The steady clock of the drivers' rate loop, advanced by hand (capture times stay real)."""

    def __init__(self) -> None:
        self.ns = 1_000_000_000_000

    @classmethod
    def install(cls, monkeypatch: pytest.MonkeyPatch) -> FakeClock:
        clock = cls()
        monkeypatch.setattr(sensor_driver, "time",
                            types.SimpleNamespace(monotonic_ns=clock.monotonic_ns, time_ns=time.time_ns))
        return clock

    def monotonic_ns(self) -> int:
        return self.ns

    def advance(self, seconds: float) -> None:
        self.ns += round(seconds * 1e9)


def test_drivers_of_one_rate_tick_together(ros, monkeypatch):
    """Drivers of one rate whose first ticks come a third of a period apart have their frames due at the same
    instants all the same: frames are due half a period before the ticks of one grid, the multiples of the timer
    period on the steady clock (sensor_driver "Shared tick grid"), so one executor wake-up serves all of them.
    Just before each such instant no driver has a new frame due, just after it every driver has one."""
    clock = FakeClock.install(monkeypatch)
    period = 0.06
    period_ns = round(period * 1e9)
    imus = []
    for index in range(3):
        imu = ros.driver(ImuDriver, f"imu{index}", rate=1 / period)
        imu._on_tick()  # its first tick: frame 0, and the timer moves onto the grid
        assert imu.published_count == 1
        # the real timer: the shortened period up to the grid was armed, its own period restored
        assert imu._timer.timer_period_ns == period_ns
        assert 0 < imu._timer.time_until_next_call() <= 1.5 * period_ns
        imus.append(imu)
        clock.advance(period / 3)

    def due_instant(k: int) -> int:  # half a period before the k-th tick of the grid
        return k * period_ns - period_ns // 2

    k = -(-clock.ns // period_ns) + 1
    clock.ns = due_instant(k) + 1_000
    for imu in imus:  # catch up to here (frame 0's tick was at most a period ago)
        imu._on_tick()
    for k in range(k + 1, k + 11):
        counts = [imu.published_count for imu in imus]
        clock.ns = due_instant(k) - 1_000
        for imu in imus:
            imu._on_tick()
        assert [imu.published_count for imu in imus] == counts, f"a frame due off the grid before instant {k}"
        clock.ns = due_instant(k) + 1_000
        for imu in imus:
            imu._on_tick()
        assert [imu.published_count for imu in imus] == [c + 1 for c in counts], f"not all due at instant {k}"
    assert all(imu.skipped_count == 0 for imu in imus)


def test_rate_loop_catches_up_and_caps_bursts(ros, monkeypatch):
    clock = FakeClock.install(monkeypatch)
    imu = ros.driver(ImuDriver, "imu", rate=100.0)
    sequences: list[int] = []
    real_make = imu.make_imu
    monkeypatch.setattr(imu, "make_imu", lambda seq, stamp: sequences.append(seq) or real_make(seq, stamp))
    assert imu.timer_period == pytest.approx(0.01) and imu.max_burst == 10

    imu._on_tick()  # first tick: frame 0; frames are due every 10 ms from half a period before it
    assert imu.published_count == 1
    clock.advance(0.004)
    imu._on_tick()  # early tick: nothing due yet
    assert imu.published_count == 1
    clock.advance(0.002)  # 6 ms after the first tick (11 ms after the origin): frame 1 due
    imu._on_tick()
    assert imu.published_count == 2
    clock.advance(0.064)  # 70 ms after the first tick: a late tick catches up to frame 7
    imu._on_tick()
    assert (imu.published_count, imu.skipped_count) == (8, 0)
    clock.advance(1.0)  # stalled for a second: 100 frames due, only max_burst published, rest skipped
    imu._on_tick()
    assert imu.published_count == 18 and imu.skipped_count == 90
    for _ in range(100):  # afterwards the loop is back in phase without drift
        clock.advance(0.01)
        imu._on_tick()
    assert imu.published_count + imu.skipped_count == math.floor((2.07 + 0.005) * 100) + 1
    assert imu.skipped_count == 90
    assert sequences == list(range(imu.published_count)), "sequence numbers must stay gap-free"


def test_skipped_frames_are_warned_about_every_five_seconds_with_every_one_counted(ros, monkeypatch):
    clock = FakeClock.install(monkeypatch)
    imu = ros.driver(ImuDriver, "imu", rate=100.0)
    warnings: list[str] = []
    monkeypatch.setattr(imu, "get_logger", lambda: types.SimpleNamespace(warning=warnings.append))
    imu._on_tick()
    for _ in range(30):  # a stall of 0.5 s before each tick: 50 due, 10 published, 40 skipped each time
        clock.advance(0.5)
        imu._on_tick()
    assert imu.skipped_count == 30 * 40
    assert warnings == ["cannot keep up with 100 Hz: skipped 40 frame(s), 40 in total",
                        "cannot keep up with 100 Hz: skipped 400 frame(s) in the last 5.0 s, 440 in total",
                        "cannot keep up with 100 Hz: skipped 400 frame(s) in the last 5.0 s, 840 in total"]


def test_rate_change_restarts_the_schedule_without_a_burst(ros, monkeypatch):
    """``rate`` set at run time: the next frame is due one new period after the change, never a catch-up burst."""
    clock = FakeClock.install(monkeypatch)
    imu = ros.driver(ImuDriver, "imu", rate=1.0)
    imu._on_tick()  # frame 0 of the 1 Hz schedule
    clock.advance(0.9)  # almost a second later, 90 frames of a 100 Hz schedule would be overdue
    result = imu.set_parameters([Parameter("rate", value=100.0)])[0]
    assert result.successful, result.reason
    assert (imu.rate, imu.get_parameter("rate").value) == (100.0, 100.0)
    assert imu.timer_period == pytest.approx(0.01) and imu.max_burst == 10
    clock.advance(0.01)
    imu._on_tick()  # one new period after the change: one frame, not 90
    assert (imu.published_count, imu.skipped_count) == (2, 0)
    for _ in range(50):
        clock.advance(0.01)
        imu._on_tick()
    assert (imu.published_count, imu.skipped_count) == (52, 0)

    result = imu.set_parameters([Parameter("rate", value=1000.0)])[0]  # faster than the 2 ms timer: 2 per tick
    assert result.successful, result.reason
    assert imu.timer_period == pytest.approx(0.002)
    for _ in range(10):
        clock.advance(0.002)
        imu._on_tick()
    assert (imu.published_count, imu.skipped_count) == (52 + 10 * 2, 0)  # 20 ms at 1 kHz

    result = imu.set_parameters([Parameter("rate", value=5000.0)])[0]  # refused: the schedule is untouched
    assert not result.successful and "parameter 'rate' must be in [0.01, 2000] Hz, got 5000.0" in result.reason
    assert imu.rate == 1000.0 and imu.get_parameter("rate").value == 1000.0


def test_lidar_rate_change_rescales_point_times(ros):
    """The ``time`` field spans one scan period, so a rate change rebuilds the scan for the new period."""
    lidar = ros.driver(LidarDriver, "lidar", points_per_scan=1024, rings=16, rate=10.0)
    assert np.frombuffer(bytes(lidar.make_cloud(1, 0).data), dtype=POINT_DTYPE)["time"].max() > 0.09
    result = lidar.set_parameters([Parameter("rate", value=20.0)])[0]
    assert result.successful, result.reason
    times = np.frombuffer(bytes(lidar.make_cloud(1, 0).data), dtype=POINT_DTYPE)["time"]
    assert 0.045 < times.max() < 1 / 20.0


def test_frame_id_change_is_used_by_the_next_frame(ros):
    camera = ros.driver(CameraDriver, "cam", width=64, height=48)
    result = camera.set_parameters([Parameter("frame_id", value="cam_left")])[0]
    assert result.successful, result.reason
    assert camera.make_image(0, 0).header.frame_id == "cam_left"
    assert camera.make_camera_info(0).header.frame_id == "cam_left"
    result = camera.set_parameters([Parameter("width", value=32)])[0]
    assert not result.successful and "read-only" in result.reason
    assert camera.make_image(1, 0).width == 64


def test_next_sequence_is_per_publisher(ros):
    camera = ros.driver(CameraDriver, "cam", width=64, height=48)
    assert [camera.next_sequence(camera.image_publisher) for _ in range(3)] == [0, 1, 2]
    assert camera.next_sequence(camera.camera_info_publisher) == 0


# ---------------------------------------------------------------------------------------------- cost
def test_frame_payloads_are_byte_buffers_not_numpy(ros):
    """The payload must reach the message as bytes: a numpy array in a uint8[] field costs ~200x more.

    (Generation cost itself is measured by benchmarks/ipc_transport.py, never asserted in a test.)
    """
    camera = ros.driver(CameraDriver, "cam", width=1920, height=1080, encoding="rgb8")
    lidar = ros.driver(LidarDriver, "lidar", points_per_scan=131072)
    for msg in (camera.make_image(0, 0), lidar.make_cloud(0, 0)):
        assert isinstance(msg.data, (array.array, bytes, bytearray)), type(msg.data)
        assert len(msg.data) in (1920 * 1080 * 3, 131072 * 24)
