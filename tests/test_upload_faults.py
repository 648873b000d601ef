"""The recorder's uploads when the store is wrong or failing, each against a real server process on loopback:
wrong credentials, a missing bucket, an unreachable endpoint, a server answering 500 (its disk full) and a
stalled server (SIGSTOP). Each is named in ``~/get_stats`` and ``/diagnostics``, nothing local is deleted (with
``upload.delete_after`` on), and once the fault is gone the uploads complete."""
from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from baglib.upload.journal import JOURNAL_NAME
from component_container.component_manager import ComponentManager
from components.recorder import upload_process
from container_process import small_filesystem
from ipc_testing import in_process_manager, wait_until
from ipc_testing.s3_server import SECRET_KEY, S3Server
from test_upload import load, unloaded_uploads_done
from upload_harness import bucket, s3, stored, unloaded_work, upload_summary  # noqa: F401 - fixtures

MIB = 1 << 20


@pytest.fixture(scope="module")
def manager() -> Any:
    with in_process_manager("upload_faults_test") as manager:
        load(manager, "ImuDriver", "imu", rate=100.0)
        yield manager


@pytest.fixture(autouse=True)
def only_the_driver_after(manager: ComponentManager) -> Iterator[None]:
    """A test that failed half-way leaves no recorder behind for the next one."""
    yield
    for component in manager.components():
        if component.full_name != "/imu":
            manager.unload(component.unique_id)


def record(manager: ComponentManager, root: Path, uri: str, endpoint: str) -> Any:
    return load(manager, "Recorder", "recorder", **{
        "storage.uri": str(root / "run"), "record.topics": ["/imu/imu"], "storage.max_bagfile_duration": 1.0,
        "upload.uri": uri, "upload.endpoint_url": endpoint, "upload.delete_after": True})


def failing_then_stopped(manager: ComponentManager, recorder: Any, root: Path, expected: str) -> None:
    """The error is reported live and, after the unload, on the container's /diagnostics; nothing local was
    deleted; then the upload process is stopped (it would retry until the container exits)."""
    error = wait_until(lambda: recorder.node.stats()["upload"]["last_error"], 30.0)
    assert error and expected in error, recorder.node.stats()["upload"]
    assert SECRET_KEY not in error and "another-secret" not in error  # no credential in a report
    health = recorder.node.health()
    assert health.values["upload error"] == error and "upload failing" in health.message, health
    manager.unload(recorder.unique_id)
    statuses = unloaded_work(manager)
    assert statuses and expected in statuses[0].message, [(s.name, s.message) for s in statuses]
    local = sorted(path.name for path in (root / "run").iterdir())
    assert len(local) >= 3 and "metadata.yaml" in local  # every file still here
    upload_process.stop(root / JOURNAL_NAME)
    assert unloaded_uploads_done(manager, 5.0)


def test_wrong_credentials_are_named_and_nothing_is_deleted(
        manager: ComponentManager, s3: S3Server, tmp_path: Path) -> None:
    """The environment has the credentials of ``s3``; the recorder is pointed at a store with another secret."""
    with S3Server(tmp_path / "other", secret_key="another-secret") as other:
        recorder = record(manager, tmp_path, "s3://bags/robot", other.endpoint_url)
        failing_then_stopped(manager, recorder, tmp_path, "refused the credentials")


def test_a_missing_bucket_is_named_and_nothing_is_deleted(
        manager: ComponentManager, s3: S3Server, tmp_path: Path) -> None:
    recorder = record(manager, tmp_path, "s3://no-such-bucket/robot", s3.endpoint_url)
    failing_then_stopped(manager, recorder, tmp_path, "the bucket does not exist")


def test_an_unreachable_endpoint_is_named_and_nothing_is_deleted(
        manager: ComponentManager, s3: S3Server, tmp_path: Path) -> None:
    nobody = S3Server(tmp_path / "never-started")  # a free port nobody listens on
    recorder = record(manager, tmp_path, "s3://bags/robot", nobody.endpoint_url)
    failing_then_stopped(manager, recorder, tmp_path, "cannot be reached")


@contextlib.contextmanager
def fault(kind: str, server: S3Server, filler: Path) -> Iterator[str]:
    """``500``: the server's disk is full (nanio answers InternalError) until the filler is deleted;
    ``stall``: the server is stopped (SIGSTOP) until it is continued."""
    if kind == "500":
        with open(filler, "wb") as stream:
            with contextlib.suppress(OSError):  # ENOSPC: the disk is full
                while True:
                    stream.write(b"\0" * MIB)
                    stream.flush()
        yield "the server answered 500"
        filler.unlink()
    else:
        server.pause()
        try:
            yield "the server stopped answering"
        finally:
            server.resume()


@pytest.mark.parametrize("kind", ["500", pytest.param("stall", marks=pytest.mark.sweep)])  # stall: 10 s timeout
def test_a_failing_server_is_named_and_the_uploads_complete_once_it_recovers(
        manager: ComponentManager, s3: S3Server, tmp_path: Path, kind: str) -> None:
    with small_filesystem(tmp_path / "store", 16 * MIB) as mounted:
        assert mounted, "needs root to mount a small tmpfs (the tests run as root in CI)"
        with S3Server(tmp_path / "store" / "data", log=tmp_path / "store.log") as server:
            server.client().create_bucket(Bucket="bags")
            with fault(kind, server, tmp_path / "store" / "filler") as expected:
                recorder = record(manager, tmp_path, "s3://bags/robot", server.endpoint_url)
                error = wait_until(lambda: recorder.node.stats()["upload"]["last_error"], 30.0)
                assert error and expected in error, recorder.node.stats()["upload"]
                assert (tmp_path / "run" / "run_0.mcap").exists()  # nothing deleted while failing
            manager.unload(recorder.unique_id)
            assert unloaded_uploads_done(manager, 60.0), upload_summary(tmp_path, "s3://bags/robot")
            summary = upload_summary(tmp_path, "s3://bags/robot")
            assert summary["complete"] and summary["files_uploaded"] >= 3 and not summary["last_error"], summary
            assert not (tmp_path / "run").exists(), sorted(p.name for p in (tmp_path / "run").iterdir())  # deleted
            assert "robot/run/metadata.yaml" in stored(server, "bags", "robot/")
