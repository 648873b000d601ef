"""Issue #11, limits on the load path: every number a request controls is bounded, and says so.

The load service and every node's parameter services answer anyone on the ROS domain. These tests drive one
real container process (``--allow-module-plugins``, for the gated recorder of container_test_plugins) the way
such a caller would: LoadNode requests with out-of-range numbers, ``~/snapshot`` calls while a snapshot is
being written, and ``ros2 param set`` (rclpy's SetParameters service) on the loaded drivers.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Iterator

import pytest
from rcl_interfaces.srv import DescribeParameters, GetParameters, SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbag2_interfaces.srv import Snapshot
from rosbags.rosbag2 import Reader
from sensor_msgs.msg import Imu
from std_srvs.srv import Trigger

from container_process import ContainerClient, ContainerProcess, Containers, listing, wait_until

IPC = {"use_intra_process_comms": True}
GATED_RECORDER = "tests.container_test_plugins:GatedRecorder"


class Rig:
    """The module's container, its ContainerClient and the probe node the tests call through."""

    def __init__(self, process: ContainerProcess, client: ContainerClient, probe: Node) -> None:
        self.process, self.client, self.probe = process, client, probe

    def call(self, srv_type: Any, service: str, request: Any, timeout: float = 10.0) -> Any:
        """Call ``service`` until it answers (Fast DDS drops the replies to a client it has not matched yet)."""
        client = self.probe.create_client(srv_type, service)
        try:
            assert client.wait_for_service(timeout_sec=timeout), f"{service} did not appear"
            answers: list[Any] = []

            def answered() -> bool:
                future = client.call_async(request)
                executor = SingleThreadedExecutor(context=self.probe.context)
                executor.add_node(self.probe)
                executor.spin_until_future_complete(future, timeout_sec=1.0)
                executor.remove_node(self.probe)
                executor.shutdown()
                if future.done():
                    answers.append(future.result())
                return future.done()

            assert wait_until(answered, timeout), f"no reply from {service} within {timeout} s"
            return answers[0]
        finally:
            self.probe.destroy_client(client)

    def load(self, plugin: str, name: str, parameters: dict[str, Any], package: str = "components") -> Any:
        return self.client.load(plugin, package, name=name, parameters=parameters, extra=IPC)

    def set_parameter(self, node: str, name: str, value: Any) -> Any:
        request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        return self.call(SetParameters, f"{node}/set_parameters", request).results[0]

    def get_parameter(self, node: str, name: str) -> Any:
        value = self.call(GetParameters, f"{node}/get_parameters", GetParameters.Request(names=[name])).values[0]
        return parameter_value_to_python(value)

    def describe(self, node: str, name: str) -> Any:
        request = DescribeParameters.Request(names=[name])
        return self.call(DescribeParameters, f"{node}/describe_parameters", request).descriptors[0]


@pytest.fixture(scope="module")
def rig(ros: None) -> Iterator[Rig]:
    probe = Node("bounds_test_probe")
    containers = Containers(probe)
    try:
        process, client = containers.start("--allow-module-plugins")
        yield Rig(process, client, probe)
    finally:
        containers.close()
        probe.destroy_node()


@pytest.fixture(autouse=True)
def healthy(rig: Rig) -> Iterator[None]:
    """After each test the shared container still runs, with nothing of the test left loaded in it."""
    yield
    left = listing(rig.client)
    for unique_id, _ in left:
        rig.client.unload(unique_id)
    assert rig.process.alive(), rig.process.output[-3000:]
    assert left == [], f"left loaded by the test: {left}"


def refused(rig: Rig, plugin: str, name: str, parameters: dict[str, Any], package: str = "components") -> str:
    """Load a component that must be refused; returns the error. The container must stay up."""
    response = rig.load(plugin, name, parameters, package)
    if response.success:  # before the bounds: do not leave a 1 GB/s camera running in the shared container
        rig.client.unload(response.unique_id)
    assert not response.success, f"{plugin} {parameters} was loaded"
    assert f"/{name}" not in [node for _, node in listing(rig.client)]
    assert rig.process.alive()
    return response.error_message


# --- LoadNode: out-of-range numbers are refused, naming the parameter and its range ------------------------------
@pytest.mark.parametrize("parameters, expected", [
    ({"storage.max_cache_size": 10**18},
     "parameter 'storage.max_cache_size' must be in [1, {half_memory}] bytes (at most half the available memory)"),
    ({"max_cache_size": 10**18}, "parameter 'max_cache_size' (alias of 'storage.max_cache_size') must be in [1, "),
    ({"storage.stall_reserve": 10**18}, "parameter 'storage.stall_reserve' must be 0 (drop as soon as max_cache_size "
                                        "is full, as rosbag2 does; -1: automatic) or in [1, {half_memory}] bytes"),
    ({"storage.stall_reserve": -2}, "parameter 'storage.stall_reserve' must be 0 (drop as soon as max_cache_size "),
    ({"record.topic_polling_interval.sec": 0, "record.topic_polling_interval.nsec": 1},
     "parameter 'record.topic_polling_interval' (.sec + .nsec) must be in [0.01, 60] s, got 1e-09"),
    ({"record.topic_polling_interval.sec": 3600},
     "parameter 'record.topic_polling_interval' (.sec + .nsec) must be in [0.01, 60] s, got 3600.1"),
    ({"storage.max_bagfile_size": 1},
     "parameter 'storage.max_bagfile_size' must be 0 (no splitting) or in [86016, 9223372036854775807] bytes, got 1"),
    ({"max_bag_size": 1024, "storage.storage_id": "sqlite3"},
     "parameter 'max_bag_size' (alias of 'storage.max_bagfile_size') must be 0 (no splitting) or in [86016, "),
    ({"storage.max_bagfile_duration": 0.001},
     "parameter 'storage.max_bagfile_duration' must be 0 (no splitting) or in [1, 31536000] s, got 0.001"),
    ({"storage.max_bagfile_duration": float("inf")},
     "parameter 'storage.max_bagfile_duration' must be 0 (no splitting) or in [1, 31536000] s, got inf"),
], ids=["cache_size", "cache_size_alias", "stall_reserve", "stall_reserve_negative", "polling_1ns", "polling_1h", "bagfile_size_1_byte", "bagfile_size_1kib",
        "bagfile_duration_1ms", "bagfile_duration_inf"])
def test_recorder_numbers_are_bounded(rig: Rig, tmp_path: Path, parameters: dict[str, Any], expected: str) -> None:
    uri = tmp_path / "never"
    error = refused(rig, "components::Recorder", "recorder_bounds",
                    {"storage.uri": str(uri), "record.topics": ["/imu/imu"], **parameters})
    half_memory = _mem_available() // 2
    prefix, _, rest = expected.partition("{half_memory}")
    assert prefix in error, error
    if rest:  # MemAvailable moves a little between the container's reading and this one
        allowed = int(error.split(prefix, 1)[1].split("]", 1)[0])
        assert abs(allowed - half_memory) < 0.1 * half_memory and rest in error, error
    assert not uri.exists()


def _mem_available() -> int:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no MemAvailable in /proc/meminfo")


@pytest.mark.parametrize("plugin, parameters, expected", [
    ("components::CameraDriver", {"width": 8192, "height": 8192},
     "parameter 'width' x 'height' x 3 bytes per pixel (rgb8), the frame size, must be in [8, 67108864] bytes, "
     "got 201326592"),
    ("components::CameraDriver", {"width": 100000, "height": 1, "encoding": "mono8"},
     "parameter 'width' must be in [1, 16384] pixels, got 100000"),
    ("components::CameraDriver", {"width": 8, "height": 8, "fps": 5000.0},
     "parameter 'fps' must be in [0.01, 2000] Hz, got 5000.0"),
    ("components::CameraDriver", {"width": 1920, "height": 1080, "fps": 1000.0},
     "parameter 'fps' must be in [0.01, 160.751] Hz for frames of 6220800 bytes (at most 1000 MB/s per driver), "
     "got 1000.0"),
    ("components::CameraDriver", {"fps": 1e-300}, "parameter 'fps' must be in [0.01, 2000] Hz, got 1e-300"),
    ("components::LidarDriver", {"points_per_scan": 4_000_000},
     "parameter 'points_per_scan' must be in [1, 2796202] points, got 4000000"),
    ("components::LidarDriver", {"rings": 4096}, "parameter 'rings' must be in [1, 1024] rings, got 4096"),
    ("components::ImuDriver", {"rate": 10_000.0}, "parameter 'rate' must be in [0.01, 2000] Hz, got 10000.0"),
    ("components::Talker", {"rate": 1e9}, "parameter 'rate' must be in [0.01, 2000] Hz, got 1000000000.0"),
], ids=["camera_200MB_frame", "camera_width", "camera_5kHz", "camera_6GBps", "camera_slowest", "lidar_points",
        "lidar_rings", "imu_10kHz", "talker_1GHz"])
def test_driver_numbers_are_bounded(rig: Rig, plugin: str, parameters: dict[str, Any], expected: str) -> None:
    error = refused(rig, plugin, "driver_bounds", parameters)
    assert expected in error, error


# --- ~/snapshot: at most one pending ----------------------------------------------------------------------------
def test_snapshot_while_one_is_pending_is_refused(rig: Rig, tmp_path: Path) -> None:
    """A snapshot waiting for the writer makes another one answer false instead of queueing a second copy of the
    ring; once it is written, the next one is taken again, and both reach the bag."""
    imu = rig.load("components::ImuDriver", "snap_imu", {"rate": 200.0})
    assert imu.success, imu.error_message
    uri = tmp_path / "snap"
    gate = tmp_path / "snap.hold"
    gate.touch()  # the writer waits before its first write until the test removes this file
    recorder = rig.load(GATED_RECORDER, "recorder_snap", {
        "storage.uri": str(uri), "record.topics": ["/snap_imu/imu"], "storage.snapshot_mode": True,
        "storage.max_cache_size": 200_000}, package="tests")
    assert recorder.success, recorder.error_message

    def counts() -> dict[str, int]:
        stats = json.loads(rig.call(Trigger, "/recorder_snap/get_stats", Trigger.Request()).message)
        return stats["current"]["topics"].get("/snap_imu/imu", {"received": 0, "written": 0})

    def snapshot() -> bool:
        return rig.call(Snapshot, "/recorder_snap/snapshot", Snapshot.Request()).success

    assert wait_until(lambda: counts()["received"] > 20, 10.0)
    assert snapshot() is True
    for _ in range(5):  # the first one is held at the gate: each of these would queue another copy of the ring
        assert snapshot() is False
    assert counts()["written"] == 0
    gate.unlink()
    released = time.time_ns()
    received = counts()["received"]
    assert wait_until(lambda: counts()["received"] > received + 5, 10.0)  # in the ring, after the first snapshot
    assert wait_until(snapshot, 10.0), "no snapshot taken after the first one was written"
    assert rig.client.unload(recorder.unique_id).success  # finalizes the bag after writing the pending snapshot
    with Reader(uri) as bag:
        log_times = [log_time for _, log_time, _ in bag.messages()]
    assert log_times and min(log_times) < released, "the first snapshot is not in the bag"
    assert max(log_times) > released, "the second snapshot is not in the bag"
    assert rig.client.unload(imu.unique_id).success
    assert "snapshot refused: the previous snapshot is still being written" in rig.process.output


# --- dynamic driver parameters -------------------------------------------------------------------------------------
def test_driver_rate_and_frame_id_change_at_run_time(rig: Rig) -> None:
    """``ros2 param set /imu rate 50.0`` and ``frame_id``: accepted, used for the next messages."""
    imu = rig.load("components::ImuDriver", "dyn_imu", {"rate": 100.0})
    assert imu.success, imu.error_message
    received: list[str] = []
    subscription = rig.probe.create_subscription(
        Imu, "/dyn_imu/imu", lambda msg: received.append(msg.header.frame_id),
        QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    try:
        assert wait_until(lambda: "imu" in received, 10.0, rig.probe)
        result = rig.set_parameter("/dyn_imu", "rate", 50.0)
        assert result.successful, result.reason
        assert rig.get_parameter("/dyn_imu", "rate") == 50.0
        result = rig.set_parameter("/dyn_imu", "frame_id", "imu_link")
        assert result.successful, result.reason
        assert rig.get_parameter("/dyn_imu", "frame_id") == "imu_link"
        assert wait_until(lambda: "imu_link" in received, 10.0, rig.probe)
        before = len(received)
        assert wait_until(lambda: len(received) >= before + 10, 10.0, rig.probe), "publishing stopped"
        switched = received.index("imu_link")
        assert set(received[switched:]) == {"imu_link"}, "old frame_id after the change"
    finally:
        rig.probe.destroy_subscription(subscription)
        assert rig.client.unload(imu.unique_id).success


@pytest.mark.parametrize("plugin, parameters, name, value, expected", [
    ("components::ImuDriver", {}, "rate", 5000.0, "parameter 'rate' must be in [0.01, 2000] Hz, got 5000.0"),
    ("components::ImuDriver", {}, "rate", 0.0, "parameter 'rate' must be in [0.01, 2000] Hz, got 0.0"),
    ("components::ImuDriver", {}, "rate", "fast", "parameter 'rate' must be a number, got 'fast'"),
    ("components::ImuDriver", {}, "frame_id", "", "parameter 'frame_id' must not be empty"),
    ("components::CameraDriver", {"width": 1920, "height": 1080, "fps": 1.0}, "fps", 500.0,
     "parameter 'fps' must be in [0.01, 160.751] Hz for frames of 6220800 bytes"),
    ("components::LidarDriver", {"points_per_scan": 1024, "rings": 16}, "rate", 2500,
     "parameter 'rate' must be in [0.01, 2000] Hz, got 2500"),
], ids=["imu_5kHz", "imu_zero", "imu_string", "empty_frame_id", "camera_throughput", "lidar_rate"])
def test_driver_parameter_change_out_of_range_is_refused(rig: Rig, plugin: str, parameters: dict[str, Any],
                                                         name: str, value: Any, expected: str) -> None:
    driver = rig.load(plugin, "dyn_driver", parameters)
    assert driver.success, driver.error_message
    try:
        before = rig.get_parameter("/dyn_driver", name)
        result = rig.set_parameter("/dyn_driver", name, value)
        assert not result.successful and expected in result.reason, result.reason
        assert rig.get_parameter("/dyn_driver", name) == before
    finally:
        assert rig.client.unload(driver.unique_id).success


@pytest.mark.parametrize("plugin, name, value, why", [
    ("components::ImuDriver", "qos", "sensor_data", "the publishers are created with it at load"),
    ("components::ImuDriver", "topic", "/elsewhere", "the publishers are created with it at load"),
    ("components::CameraDriver", "width", 320, "the frame geometry sizes the buffers precomputed at load"),
    ("components::CameraDriver", "encoding", "mono8", "the frame geometry sizes the buffers precomputed at load"),
    ("components::LidarDriver", "points_per_scan", 1024, "the frame geometry sizes the buffers precomputed at load"),
], ids=["qos", "topic", "camera_width", "camera_encoding", "lidar_points"])
def test_fixed_driver_parameters_say_why(rig: Rig, plugin: str, name: str, value: Any, why: str) -> None:
    driver = rig.load(plugin, "fixed_driver", {})
    assert driver.success, driver.error_message
    try:
        descriptor = rig.describe("/fixed_driver", name)
        assert descriptor.read_only and f"read-only: {why}" in descriptor.description, descriptor
        assert not rig.set_parameter("/fixed_driver", name, value).successful
        for dynamic in ("frame_id", "fps" if plugin.endswith("CameraDriver") else "rate"):
            descriptor = rig.describe("/fixed_driver", dynamic)
            assert not descriptor.read_only and "can be changed at run time" in descriptor.description
    finally:
        assert rig.client.unload(driver.unique_id).success
