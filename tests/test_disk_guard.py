"""The recorder on a filling disk, with a limited number of files, and with its file deleted under it.

Real container processes over Fast DDS: one container per module (camera and IMU, intra-process), each test
loads its recorder next to them and leaves the container as it found it; the small disk is a real tmpfs (the
tests need root to mount one, as test_recorder's disk-full test does); bags are read back with rosbags.
"""
from __future__ import annotations

import json
import os
import pathlib
from typing import Any, Iterator

import pytest
import yaml
from rclpy.node import Node
from rosbags.rosbag2 import Reader
from std_srvs.srv import Trigger

from container_process import ContainerClient, Containers, call, listing, small_filesystem, wait_until

CAMERA = {"width": 320, "height": 240, "fps": 30.0}  # ~7 MB/s
MIB = 1024 * 1024
DRIVERS = ["/camera", "/imu"]


def get_stats(probe: Node, recorder: str = "/recorder") -> dict[str, Any]:
    """The recorder's ~/get_stats, sent again until answered (Fast DDS drops replies to brand-new clients)."""
    client = probe.create_client(Trigger, f"{recorder}/get_stats")
    try:
        return json.loads(call(probe, client, Trigger.Request(), 10.0, again=True).message)
    finally:
        probe.destroy_client(client)


def bag_messages(uri: pathlib.Path) -> int:
    with Reader(uri) as reader:
        return sum(1 for _ in reader.messages())


@pytest.fixture(scope="module")
def rig_module(ros: None) -> Iterator[tuple[Any, ContainerClient, Node]]:
    """A container with a camera and an IMU, shared by the module's tests."""
    probe = Node("disk_guard_probe")
    started = Containers(probe)
    try:
        process, client = started.start("--use-intra-process-comms")
        assert client.load("components::CameraDriver", parameters=CAMERA).success
        assert client.load("components::ImuDriver", parameters={"rate": 100.0}).success
        yield process, client, probe
        assert process.stop() == 0, process.output[-3000:]
    finally:
        started.close()
        client.destroy()
        probe.destroy_node()


@pytest.fixture()
def rig(rig_module: tuple[Any, ContainerClient, Node]) -> Iterator[tuple[Any, ContainerClient, Node]]:
    """The shared container; after each test it still runs its two drivers, and no recorder is left."""
    yield rig_module
    process, client, _ = rig_module
    for unique_id, name in listing(client):
        if name not in DRIVERS:
            client.unload(unique_id)
    assert process.alive(), process.output[-3000:]
    assert [name for _, name in listing(client)] == DRIVERS


def load_recorder(client: ContainerClient, **parameters: Any) -> int:
    loaded = client.load("components::Recorder", parameters=parameters)
    assert loaded.success, loaded
    return loaded.unique_id


@pytest.fixture()
def small_disk(tmp_path: pathlib.Path):
    with small_filesystem(tmp_path / "small", 24 * MIB) as mounted:
        if not mounted:
            pytest.fail("this test needs a tmpfs (run as root)")
        yield tmp_path / "small"


def test_free_space_guard_stops_cleanly_before_the_disk_is_full(rig: Any, small_disk: pathlib.Path) -> None:
    process, client, probe = rig
    uri = small_disk / "guarded"
    recorder = load_recorder(client, **{"storage.uri": str(uri), "storage.min_free_space": 16 * MIB,
                                        "record.topics": ["/camera/image_raw", "/imu/imu"]})
    early = wait_until(lambda: get_stats(probe)["current"]["seconds_until_min_free"], 5.0)
    assert early and 0 < early < 60, early  # ~8 MiB to go at ~7 MB/s
    stats = wait_until(lambda: (s := get_stats(probe)["current"])["error"] and s, 20.0)
    assert stats, "the guard never stopped the recorder"
    assert f"below storage.min_free_space ({16 * MIB} bytes)" in stats["error"]
    free = os.statvfs(small_disk).f_bavail * os.statvfs(small_disk).f_frsize
    assert free > 8 * MIB, f"the disk was allowed to fill up: {free} bytes free"
    assert wait_until((uri / "metadata.yaml").exists, 5.0)  # finalized at once, not at unload
    assert bag_messages(uri) > 0
    assert [name for _, name in listing(client)] == [*DRIVERS, "/recorder"]
    assert client.unload(recorder).success
    refused = client.load("components::Recorder", name="second", parameters={
        "storage.uri": str(small_disk / "refused"), "storage.min_free_space": 32 * MIB})  # more than the disk
    assert not refused.success and "parameter 'storage.min_free_space'" in refused.error_message, refused
    assert not (small_disk / "refused").exists()


def test_circular_recording_keeps_the_newest_files(rig: Any, tmp_path: pathlib.Path) -> None:
    """Split by size (every image is bigger than the smallest limit, so each file holds one or two): the oldest
    files go as new ones open. (Circular recording split by duration: test_bag_writer.)"""
    process, client, probe = rig
    uri = tmp_path / "circular"
    recorder = load_recorder(client, **{"storage.uri": str(uri), "storage.max_bagfile_size": 86016,
                                        "storage.max_bag_files": 2, "record.topics": ["/camera/image_raw"]})
    assert wait_until(lambda: len(get_stats(probe)["current"]["deleted_files"]) >= 2, 15.0)
    stop = probe.create_client(Trigger, "/recorder/stop_recording")
    final = json.loads(call(probe, stop, Trigger.Request(), 30.0).message)
    probe.destroy_client(stop)
    assert client.unload(recorder).success
    counts = final["topics"]["/camera/image_raw"]  # written: every message, the deleted files' included
    assert counts["written"] == counts["received"] - counts["dropped"] > bag_messages(uri), counts
    meta = yaml.safe_load((uri / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    on_disk = sorted(p.name for p in uri.glob("*.mcap"))
    assert sorted(meta["relative_file_paths"]) == on_disk and len(on_disk) == 2
    assert f"{uri.name}_0.mcap" not in on_disk and f"{uri.name}_1.mcap" not in on_disk  # the oldest went first
    assert meta["message_count"] == sum(f["message_count"] for f in meta["files"]) == bag_messages(uri)
    assert meta["topics_with_message_count"][0]["message_count"] == meta["message_count"]


def test_a_deleted_bag_file_is_a_storage_failure(rig: Any, tmp_path: pathlib.Path) -> None:
    process, client, probe = rig
    uri = tmp_path / "deleted"
    load_recorder(client, **{"storage.uri": str(uri), "record.topics": ["/imu/imu"]})
    current = pathlib.Path(wait_until(lambda: get_stats(probe)["current"]["current_file"], 5.0))
    assert wait_until(lambda: get_stats(probe)["current"]["topics"].get("/imu/imu", {}).get("written", 0) >= 5,
                      10.0)
    current.unlink()
    error = wait_until(lambda: get_stats(probe)["current"]["error"], 5.0)
    assert error and "the bag file was deleted while recording" in error, error
    # the writer thread finalizes the bag right after reporting the error
    assert wait_until(lambda: (uri / "metadata.yaml").exists(), 10.0)
    meta = yaml.safe_load((uri / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert current.name not in meta["relative_file_paths"]
    assert [name for _, name in listing(client)] == [*DRIVERS, "/recorder"]
