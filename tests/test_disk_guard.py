"""The recorder on a filling disk, with a limited number of files, and with its file deleted under it.

Real container processes over Fast DDS; the small disk is a real tmpfs (the tests need root to mount one, as
test_recorder's disk-full test does); bags are read back with rosbags.
"""
from __future__ import annotations

import json
import os
import pathlib
import time
from typing import Any

import pytest
import rclpy
import yaml
from rclpy.node import Node
from rosbags.rosbag2 import Reader
from std_srvs.srv import Trigger

from container_process import ContainerClient, Containers, listing, small_filesystem, wait_until

CAMERA = {"width": 320, "height": 240, "fps": 30.0}  # ~7 MB/s
MIB = 1024 * 1024


def get_stats(probe: Node, recorder: str = "/recorder") -> dict[str, Any]:
    """The recorder's ~/get_stats, retried until answered (Fast DDS drops replies to brand-new clients)."""
    client = probe.create_client(Trigger, f"{recorder}/get_stats")
    try:
        assert client.wait_for_service(timeout_sec=10.0)
        for _ in range(10):
            future = client.call_async(Trigger.Request())
            deadline = time.monotonic() + 2.0
            while not future.done() and time.monotonic() < deadline:
                rclpy.spin_once(probe, timeout_sec=0.05)
            if future.done():
                return json.loads(future.result().message)
        raise AssertionError(f"{recorder}/get_stats never answered")
    finally:
        probe.destroy_client(client)


def bag_messages(uri: pathlib.Path) -> int:
    with Reader(uri) as reader:
        return sum(1 for _ in reader.messages())


def recording_rig(containers: Containers, **recorder: Any) -> tuple[Any, ContainerClient]:
    """A container with a camera and an IMU, and a recorder with these parameters next to them."""
    process, client = containers.start("--use-intra-process-comms")
    assert client.load("components::CameraDriver", parameters=CAMERA).success
    assert client.load("components::ImuDriver", parameters={"rate": 100.0}).success
    loaded = client.load("components::Recorder", parameters=recorder)
    assert loaded.success, loaded
    return process, client


@pytest.fixture()
def small_disk(tmp_path: pathlib.Path):
    with small_filesystem(tmp_path / "small", 48 * MIB) as mounted:
        if not mounted:
            pytest.fail("this test needs a tmpfs (run as root)")
        yield tmp_path / "small"


def test_free_space_guard_stops_cleanly_before_the_disk_is_full(containers: Containers, probe: Node,
                                                               small_disk: pathlib.Path) -> None:
    uri = small_disk / "guarded"
    process, client = recording_rig(containers, **{"storage.uri": str(uri), "storage.min_free_space": 32 * MIB,
                                                   "record.topics": ["/camera/image_raw", "/imu/imu"]})
    early = wait_until(lambda: get_stats(probe)["current"]["seconds_until_min_free"], 5.0)
    assert early and 0 < early < 60, early  # ~16 MiB to go at ~7 MB/s
    stats = wait_until(lambda: (s := get_stats(probe)["current"])["error"] and s, 20.0)
    assert stats, "the guard never stopped the recorder"
    assert "below storage.min_free_space (33554432 bytes)" in stats["error"]
    free = os.statvfs(small_disk).f_bavail * os.statvfs(small_disk).f_frsize
    assert free > 24 * MIB, f"the disk was allowed to fill up: {free} bytes free"
    assert wait_until((uri / "metadata.yaml").exists, 5.0)  # finalized at once, not at unload
    assert bag_messages(uri) > 0
    assert [name for _, name in listing(client)] == ["/camera", "/imu", "/recorder"]
    assert client.unload(3).success
    refused = client.load("components::Recorder", name="second", parameters={
        "storage.uri": str(small_disk / "refused"), "storage.min_free_space": 64 * MIB})
    assert not refused.success and "parameter 'storage.min_free_space'" in refused.error_message, refused
    assert not (small_disk / "refused").exists()
    assert process.stop() == 0


def test_circular_recording_keeps_the_newest_files(containers: Containers, probe: Node,
                                                   tmp_path: pathlib.Path) -> None:
    uri = tmp_path / "circular"
    process, client = recording_rig(containers, **{"storage.uri": str(uri), "storage.max_bagfile_duration": 1,
                                                   "storage.max_bag_files": 2, "record.topics": ["/imu/imu"]})
    assert wait_until(lambda: len(get_stats(probe)["current"]["deleted_files"]) >= 2, 15.0)
    assert client.unload(3).success
    meta = yaml.safe_load((uri / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    on_disk = sorted(p.name for p in uri.glob("*.mcap"))
    assert sorted(meta["relative_file_paths"]) == on_disk and len(on_disk) == 2
    assert f"{uri.name}_0.mcap" not in on_disk  # the oldest went first
    assert meta["message_count"] == sum(f["message_count"] for f in meta["files"]) == bag_messages(uri)
    assert meta["topics_with_message_count"][0]["message_count"] == meta["message_count"]
    assert process.stop() == 0


def test_a_deleted_bag_file_is_a_storage_failure(containers: Containers, probe: Node,
                                                 tmp_path: pathlib.Path) -> None:
    uri = tmp_path / "deleted"
    process, client = recording_rig(containers, **{"storage.uri": str(uri), "record.topics": ["/imu/imu"]})
    current = pathlib.Path(wait_until(lambda: get_stats(probe)["current"]["current_file"], 5.0))
    time.sleep(0.5)
    current.unlink()
    error = wait_until(lambda: get_stats(probe)["current"]["error"], 5.0)
    assert error and "the bag file was deleted while recording" in error, error
    meta = yaml.safe_load((uri / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert current.name not in meta["relative_file_paths"]
    assert [name for _, name in listing(client)] == ["/camera", "/imu", "/recorder"]
    assert process.stop() == 0
