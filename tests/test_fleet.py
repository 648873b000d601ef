"""Fleet recording across computers: three hosts as network namespaces on a private bridge (ipc_testing.netns),
each running a container with a camera, a LiDAR and an IMU driver, driven by ``ipc-component record`` from a
fourth namespace, the operator's, exactly as a user on a laptop would drive a robot's computers.

What is checked is exact: each container also holds a reference recorder (node ``reference``, no window, local
only) that receives every in-process message with the *same* receive timestamp as the fleet recorder (the
intra-process manager stamps a publication once for all its subscriptions). The fleet bag of a host must be
exactly the reference's messages received within [start, stop) on that host's clock: nothing missing, nothing
twice, nothing outside, per topic, by sequence number. One host is cut off the network for 3 s in the middle of
the recording; its bag must not show it.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from baglib.format import fleet_keys
from ipc_testing import ContainerProcess
from ipc_testing.netns import Network, unavailable
from ipc_testing.process import run_command

pytestmark = pytest.mark.skipif(unavailable() is not None, reason=f"no network namespaces: {unavailable()}")

REPO = Path(__file__).resolve().parents[1]
HOSTS = ("h1", "h2", "h3")
RIG = [
    {"plugin": "components::CameraDriver", "name": "camera", "parameters": {"width": 160, "height": 120, "fps": 30.0}},
    {"plugin": "components::LidarDriver", "name": "lidar", "parameters": {"points_per_scan": 2048, "rings": 16,
                                                                            "rate": 10.0}},
    {"plugin": "components::ImuDriver", "name": "imu", "parameters": {"rate": 100.0}},
    {"plugin": "components::Recorder", "name": "reference",
     "parameters": {"storage.uri": "reference", "record.all_topics": True, "record.local_only": True}},
]
SEQUENCED = {"/camera/image_raw": "sensor_msgs/msg/Image", "/lidar/points": "sensor_msgs/msg/PointCloud2",
             "/imu/imu": "sensor_msgs/msg/Imu"}
RECORD_SECONDS = 7.0
PARTITION_SECONDS = 3.0
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def sequence_of(topic: str, message: Any) -> int:
    if topic == "/imu/imu":
        return int(message.orientation_covariance[1])
    return int.from_bytes(bytes(message.data[:8]), "little")


def received(bag: Path, prefix: str = "") -> dict[str, list[tuple[int, int]]]:
    """Per sequenced topic: (receive time, sequence number) of every message, in the bag's order (read with
    rosbags, an independent reader); ``prefix``: the topics are under it (a merged bag's ``--prefix-host``)."""
    found: dict[str, list[tuple[int, int]]] = {topic: [] for topic in SEQUENCED}
    with Reader(bag) as reader:
        connections = [c for c in reader.connections if c.topic.removeprefix(prefix) in SEQUENCED]
        for connection, log_time, data in reader.messages(connections=connections):
            message = TYPESTORE.deserialize_cdr(data, connection.msgtype)
            topic = connection.topic.removeprefix(prefix)
            found[topic].append((log_time, sequence_of(topic, message)))
    return found


class Fleet:
    """The network, its containers and the operator's command line."""

    def __init__(self, network: Network, workdir: Path) -> None:
        self.network, self.workdir = network, workdir
        self.ros_env = network.environment(int(os.environ["ROS_DOMAIN_ID"]))
        self.env = dict(os.environ, **self.ros_env)
        self.containers: dict[str, ContainerProcess] = {}

    def start_container(self, host: str) -> ContainerProcess:
        root = self.workdir / host
        root.mkdir()
        load = self.workdir / f"{host}.yaml"
        load.write_text(yaml.safe_dump({"components": [
            {"package": "components", **entry, "extra_arguments": {"use_intra_process_comms": True}}
            for entry in RIG]}))
        process = ContainerProcess("--use-intra-process-comms", "--bag-root", str(root), "--load", str(load),
                                   name=f"/{host}/container", cwd=REPO, env=self.ros_env, prefix=self.network.prefix(host),
                                   log_path=self.workdir / f"{host}.log")
        self.containers[host] = process
        return process

    def cli(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
        return run_command([*self.network.prefix("operator"), sys.executable, "-m", "ipc_component.cli", *args],
                           timeout, env=self.env, cwd=REPO)

    def stop_all(self) -> None:
        for process in self.containers.values():
            process.stop()


@pytest.fixture
def fleet(tmp_path: Path) -> Any:
    with Network(HOSTS) as network:
        fleet = Fleet(network, tmp_path)
        try:
            yield fleet
        finally:
            for process in fleet.containers.values():
                process.kill()


def _wait_for_containers(fleet: Fleet, deadline: float) -> None:
    """Until the operator lists every container with its four components."""
    while True:
        listing = fleet.cli("list")
        if all(f"/{h}/container" in listing.stdout for h in HOSTS) and listing.stdout.count("/reference") == 3:
            return
        assert time.monotonic() < deadline, f"containers not listed: {listing.stdout}{listing.stderr}"


@pytest.mark.long
def test_three_hosts_record_one_window_exactly_through_a_partition(fleet: Fleet) -> None:
    for host in HOSTS:
        fleet.start_container(host)
    _wait_for_containers(fleet, time.monotonic() + 60)

    started = fleet.cli("record", "start", "--session", "drive", "--in", "2", "--max-duration", "120")
    assert started.returncode == 0, started.stdout + started.stderr
    for host in HOSTS:
        assert f"/{host}/container" in started.stdout, started.stdout
    status = fleet.cli("record", "status", "--session", "drive")
    assert status.returncode == 0, status.stderr
    assert all(f"/{host}/container" in status.stdout for host in HOSTS), status.stdout

    time.sleep(2 + (RECORD_SECONDS - PARTITION_SECONDS) / 2)  # the recording's middle: cut h2 off the network
    fleet.network.cut("h2")
    time.sleep(PARTITION_SECONDS)
    fleet.network.mend("h2")
    time.sleep((RECORD_SECONDS - PARTITION_SECONDS) / 2)
    stopped = fleet.cli("record", "stop", "--session", "drive")
    assert stopped.returncode == 0, stopped.stdout + stopped.stderr
    fleet.stop_all()  # finalizes the reference bags

    bags = [fleet.workdir / host / "drive" / f"{host}_{host}_container" for host in HOSTS]
    merged = fleet.workdir / "merged"
    merge = fleet.cli("bag", "merge", str(merged), *map(str, bags), "--prefix-host")
    assert merge.returncode == 0, merge.stdout + merge.stderr
    cuts = []
    for host, bag in zip(HOSTS, bags):
        root = fleet.workdir / host
        custom = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["custom_data"]
        assert custom[fleet_keys.SESSION] == "drive" and custom[fleet_keys.HOST] == host, custom
        offset = int(custom[fleet_keys.CLOCK_OFFSET_NS])
        start = int(custom[fleet_keys.START_NS]) + offset
        stop = int(custom[fleet_keys.STOP_NS]) + int(custom[fleet_keys.STOP_CLOCK_OFFSET_NS])
        assert abs(offset) <= int(custom[fleet_keys.CLOCK_OFFSET_UNCERTAINTY_NS]) + 1_000_000, custom  # one clock
        recorded, reference = received(bag), received(root / "reference")
        assert received(merged, prefix=f"/{host}") == recorded, f"{host}: the merged bag differs from its bag"
        for topic in SEQUENCED:
            expected = [(t, seq) for t, seq in reference[topic] if start <= t < stop]
            assert expected, (host, topic, "the reference has nothing in the window")
            assert recorded[topic] == expected, (
                f"{host} {topic}: fleet bag differs from the window [{start}, {stop}) of the reference: "
                f"{len(recorded[topic])} vs {len(expected)} messages; only in the fleet bag "
                f"{sorted(set(recorded[topic]) - set(expected))[:5]}, only in the reference "
                f"{sorted(set(expected) - set(recorded[topic]))[:5]}; reference around the stop "
                f"{[item for item in reference[topic] if abs(item[0] - stop) < 200_000_000]}")
            sequences = [seq for _t, seq in expected]
            assert sequences == list(range(sequences[0], sequences[0] + len(sequences))), (host, topic, "a gap")
            assert reference[topic][0][0] < start and reference[topic][-1][0] >= stop, (
                host, topic, "the reference must cover the window on both sides")
            cuts.append((host, topic, (expected[0][0] - start) / 1e6, (stop - expected[-1][0]) / 1e6))
    print(stopped.stdout)
    print("cut distances (ms after the start, before the stop):", cuts)
