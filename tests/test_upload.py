"""The recorder's uploads (``upload.*``) against a real S3 server process (nanio) on loopback: every file a split
closes reaches the store whole and verified, ``metadata.yaml`` last, through a server that is killed and started
again in the middle; a bag root that fills while the store is down loses nothing; bad parameters are load
errors that name them. (SIGKILL of the container mid-upload: test_upload_resume.py; the command line:
test_bag_upload.py.)"""
from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from component_container.component_manager import ComponentManager
from component_container.startup_file import load_request
from container_process import small_filesystem
from ipc_testing import in_process_manager, wait_until
from ipc_testing.s3_server import S3Server
from upload_harness import (bucket, download, s3, sha256, stored, unloaded_work,  # noqa: F401 - fixtures
                            upload_summary)

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
IPC = {"use_intra_process_comms": True}
MIB = 1 << 20
DRIVERS = ("/imu", "/cam")


def load(manager: ComponentManager, plugin: str, name: str, **parameters: Any) -> Any:
    return manager.load(load_request({"package": "components", "plugin": f"components::{plugin}", "name": name,
                                      "parameters": parameters, "extra_arguments": IPC}, 1))


@pytest.fixture(scope="module")
def manager() -> Any:
    with in_process_manager("upload_test") as manager:
        load(manager, "ImuDriver", "imu", rate=100.0)
        load(manager, "CameraDriver", "cam", width=320, height=240, fps=30.0, topic="/cam/image_raw")
        yield manager


@pytest.fixture(autouse=True)
def only_the_drivers_after(manager: ComponentManager) -> Iterator[None]:
    """A test that failed half-way leaves no recorder behind for the next one."""
    yield
    for component in manager.components():
        if component.full_name not in DRIVERS:
            manager.unload(component.unique_id)


def imu_sequences(bag: Path) -> list[int]:
    with Reader(bag) as reader:
        connections = [c for c in reader.connections if c.topic == "/imu/imu"]
        return [int(TYPESTORE.deserialize_cdr(data, "sensor_msgs/msg/Imu").orientation_covariance[1])
                for _, _, data in reader.messages(connections=connections)]


def unloaded_uploads_done(manager: ComponentManager, timeout: float) -> bool:
    """The container's /diagnostics stop listing an unloaded recorder's uploads (they completed)."""
    return bool(wait_until(lambda: not unloaded_work(manager), timeout))


@pytest.mark.parametrize("seconds, split, outage", [(8.0, 1.0, 3.0), pytest.param(60.0, 5.0, 10.0,
                                                                                     marks=pytest.mark.sweep)])
def test_every_split_file_reaches_the_store_whole_through_a_server_restart(
        manager: ComponentManager, s3: S3Server, bucket: str, tmp_path: Path, seconds: float, split: float,
        outage: float) -> None:
    """A recording split every ``split`` s while the server is killed for ``outage`` s in the middle: every file
    and ``metadata.yaml`` is in the bucket, byte-identical, and the bag downloaded from it has no IMU gap."""
    uri = f"s3://{bucket}/robot"
    bag = tmp_path / "bags" / "run"
    recorder = load(manager, "Recorder", "recorder", **{
        "storage.uri": str(bag), "record.topics": ["/imu/imu", "/cam/image_raw"],
        "storage.max_bagfile_duration": split, "upload.uri": uri, "upload.endpoint_url": s3.endpoint_url})
    assert wait_until(lambda: recorder.node.stats()["upload"]["files_uploaded"] >= 1, 20.0), \
        recorder.node.stats()["upload"]
    s3.kill()
    try:
        errors = wait_until(lambda: recorder.node.stats()["upload"]["last_error"], outage + 10.0)
        assert errors and ("cannot be reached" in errors or "closed the connection" in errors), errors
        time.sleep(max(0.0, outage - 0.1))  # the outage itself: the recording goes on meanwhile
    finally:
        s3.start()
    time.sleep(max(0.0, seconds - outage - split))
    manager.unload(recorder.unique_id)
    assert unloaded_uploads_done(manager, 90.0), upload_summary(bag.parent, uri)
    summary = upload_summary(bag.parent, uri)
    assert summary["complete"] and not summary["deleted_before_upload"], summary
    local = {f"robot/run/{path.name}": path.read_bytes() for path in bag.iterdir()}
    remote = stored(s3, bucket, "robot/")
    assert len(local) >= seconds / split and set(remote) == set(local), (sorted(remote), sorted(local))
    assert all(sha256(remote[key]) == sha256(data) for key, data in local.items())
    sequences = imu_sequences(download(s3, bucket, "robot/run", tmp_path / "downloaded" / "run"))
    assert len(sequences) > 50 * seconds and sequences == list(range(sequences[0], sequences[0] + len(sequences)))


def test_a_bag_root_that_fills_while_the_store_is_down_deletes_nothing_unverified(
        manager: ComponentManager, s3: S3Server, bucket: str, tmp_path: Path) -> None:
    """``upload.delete_after`` on a small disk: while the server is down nothing is deleted and the disk guard
    stops the recording before the disk fills; once the server is back every file is uploaded, verified and only
    then deleted here; no file was lost and the free space never fell below the guard's minimum."""
    with small_filesystem(tmp_path / "small", 24 * MIB) as mounted:
        assert mounted, "needs root to mount a small tmpfs (the tests run as root in CI)"
        root = tmp_path / "small"
        uri = f"s3://{bucket}/small"
        lowest = [os.statvfs(root).f_bavail * os.statvfs(root).f_frsize]
        watching = threading.Event()

        def watch() -> None:
            while not watching.wait(0.01):
                lowest[0] = min(lowest[0], os.statvfs(root).f_bavail * os.statvfs(root).f_frsize)

        watcher = threading.Thread(target=watch)
        watcher.start()
        s3.kill()
        try:
            recorder = load(manager, "Recorder", "recorder", **{
                "storage.uri": str(root / "run"), "record.topics": ["/imu/imu", "/cam/image_raw"],
                "storage.max_bagfile_size": 2 * MIB, "storage.min_free_space": 8 * MIB, "upload.uri": uri,
                "upload.endpoint_url": s3.endpoint_url, "upload.delete_after": True})
            stopped = wait_until(lambda: (recorder.node.stats()["current"] or {}).get("error"), 30.0)
            assert stopped and "storage.min_free_space" in stopped, recorder.node.stats()["current"]
            # The session reports its error before it has closed the bag: metadata.yaml may still be being
            # replaced (through a hidden temporary); the bag's files are all there already.
            files = sorted(path.name for path in (root / "run").iterdir() if not path.name.startswith("."))
            assert recorder.node.stats()["upload"]["files_pending"] >= 2
        finally:
            s3.start()
        try:
            manager.unload(recorder.unique_id)
            assert unloaded_uploads_done(manager, 60.0), upload_summary(root, uri)
        finally:
            watching.set()
            watcher.join()
        summary = upload_summary(root, uri)
        assert summary["complete"] and summary["deleted_before_upload"] == 0, summary
        assert not (root / "run").exists()  # every file verified, then deleted, then the directory
        remote = stored(s3, bucket, "small/run/")
        assert sorted(key.rpartition("/")[2] for key in remote) == files
        assert lowest[0] >= 4 * MIB, f"the free space fell to {lowest[0]} bytes"


@pytest.mark.parametrize("parameters, message", [
    ({"upload.uri": "/data/bags"}, "is not an s3:// URI"),
    ({"upload.uri": "s3://user:secret@bucket/x"}, "must not carry credentials"),
    ({"upload.uri": "s3://Bad_Bucket/x"}, "not a valid bucket name"),
    ({"upload.uri": "s3://bucket/x", "upload.max_rate": -1}, "'upload.max_rate' must be >= 0"),
    ({"upload.uri": "s3://bucket/x", "upload.endpoint_url": "ftp://host"}, "'upload.endpoint_url' must be"),
])
def test_bad_upload_parameters_are_load_errors_that_name_them(
        manager: ComponentManager, tmp_path: Path, parameters: dict[str, Any], message: str) -> None:
    with pytest.raises(Exception) as refused:
        load(manager, "Recorder", "recorder", **{"storage.uri": str(tmp_path / "bag"), **parameters})
    assert message in str(refused.value)
    assert "secret" not in str(refused.value)
    assert not (tmp_path / "bag").exists()
    assert tuple(c.full_name for c in manager.components()) == DRIVERS


def test_the_disk_guard_takes_back_verified_files_first(
        manager: ComponentManager, s3: S3Server, bucket: str, tmp_path: Path) -> None:
    """On a 16 MiB tmpfs a recording of more than the disk holds (20 MiB) goes on: the free-space guard deletes
    files verified in the store, oldest first, instead of stopping; none was lost."""
    with small_filesystem(tmp_path / "small", 16 * MIB) as mounted:
        assert mounted, "needs root to mount a small tmpfs (the tests run as root in CI)"
        root = tmp_path / "small"
        uri = f"s3://{bucket}/guard"
        # 10 of the camera's 30 frames a second (2.3 MB/s): the uploads keep up on a loaded machine too, so there
        # are verified files to take back when the disk runs low (with none, stopping is right)
        recorder = load(manager, "Recorder", "recorder", **{
            "storage.uri": str(root / "run"), "record.topics": ["/cam/image_raw"],
            "record.max_rates": ["/cam/image_raw:10"], "storage.max_bagfile_size": MIB,
            "storage.min_free_space": 6 * MIB, "upload.uri": uri, "upload.endpoint_url": s3.endpoint_url})
        assert wait_until(lambda: recorder.node.stats()["current"]["bytes_written"] > 20 * MIB, 40.0), \
            recorder.node.stats()["current"]
        assert not recorder.node.stats()["current"]["error"]
        manager.unload(recorder.unique_id)
        assert unloaded_uploads_done(manager, 60.0)
        summary = upload_summary(root, uri)
        assert summary["complete"] and summary["deleted_before_upload"] == 0, summary
        remote = stored(s3, bucket, "guard/run/")
        here = {path.name for path in (root / "run").iterdir()}
        assert len(remote) > len(here) and here <= {key.rpartition("/")[2] for key in remote}


def test_circular_recording_counts_the_files_it_deletes_before_they_are_uploaded(
        manager: ComponentManager, s3: S3Server, bucket: str, tmp_path: Path) -> None:
    """Circular recording (``storage.max_bag_files``) with the store down: each file it deletes unverified is
    counted as ``deleted_before_upload``, and what it kept is uploaded once the store is back."""
    root = tmp_path  # the ordinary disk
    uri = f"s3://{bucket}/circular"
    s3.kill()
    try:
        recorder = load(manager, "Recorder", "recorder", **{
            "storage.uri": str(root / "circular"), "record.topics": ["/imu/imu"],
            "storage.max_bagfile_duration": 1.0, "storage.max_bag_files": 2, "upload.uri": uri,
            "upload.endpoint_url": s3.endpoint_url})
        assert wait_until(lambda: recorder.node.stats()["upload"]["deleted_before_upload"] >= 2, 20.0), \
            recorder.node.stats()["upload"]
    finally:
        s3.start()
    manager.unload(recorder.unique_id)
    assert unloaded_uploads_done(manager, 60.0)
    summary = upload_summary(root, uri)
    kept = sorted(path.name for path in (root / "circular").iterdir())
    assert summary["complete"] and summary["deleted_before_upload"] >= 2, summary
    assert sorted(key.rpartition("/")[2] for key in stored(s3, bucket, "circular/circular/")) == kept
