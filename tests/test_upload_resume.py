"""Uploads cut by SIGKILL of the container go on from their last confirmed part: by the next recorder loaded
over the same bag root with the same ``upload.uri``, or by ``bag upload --resume``. Real container processes, a
real nanio server, the journal read as the kill left it."""
from __future__ import annotations

import sqlite3
import subprocess
from pathlib import Path
from typing import Any

import pytest
from rclpy.node import Node

from baglib.upload.journal import JOURNAL_NAME
from container_process import Containers, recorder_stats
from ipc_testing import wait_until
from ipc_testing.s3_server import S3Server
from test_cli import cli
from upload_harness import bucket, s3, sha256, stored, upload_summary  # noqa: F401 - fixtures

MB = 1_000_000


def journal_rows(root: Path) -> dict[str, dict[str, Any]]:
    """Each file's row of the journal: name -> state, size, sent, reused, confirmed parts."""
    with sqlite3.connect(root / JOURNAL_NAME, timeout=10.0) as db:
        rows = db.execute("SELECT id, local, state, size, sent, reused FROM files").fetchall()
        parts = dict(db.execute("SELECT file_id, COUNT(*) FROM parts GROUP BY file_id").fetchall())
    return {Path(local).name: {"state": state, "size": size, "sent": sent, "reused": reused,
                               "parts": parts.get(id_, 0)} for id_, local, state, size, sent, reused in rows}


def upload_processes(root: Path) -> list[str]:
    listing = subprocess.run(["pgrep", "-af", f"baglib.upload.worker {root / JOURNAL_NAME}"], capture_output=True,
                             text=True).stdout
    return [line for line in listing.splitlines() if "pgrep" not in line]


@pytest.mark.parametrize("resumer", ["recorder", pytest.param("bag upload --resume", marks=pytest.mark.sweep)])
def test_a_killed_containers_upload_resumes_from_its_last_confirmed_part(
        containers: Containers, probe: Node, s3: S3Server, bucket: str, tmp_path: Path, resumer: str) -> None:
    uri = f"s3://{bucket}/fleet"
    process, client = containers.start("--use-intra-process-comms")
    camera = client.load("components::CameraDriver", parameters={"width": 640, "height": 480, "fps": 30.0})
    assert camera.success, camera
    # The killed container's upload process sends on until it sees its parent gone (PARENT_POLL, later at nice +10
    # on a loaded machine): at 24 MB/s it once sent the whole rest of the 62 MB file meanwhile, and the second
    # recorder had nothing left to resume. At 8 MB/s that tail stays well under the 45 MB left after two parts.
    recorder = client.load("components::Recorder", parameters={
        "storage.uri": str(tmp_path / "first"), "record.topics": ["/camera/image_raw"], "upload.uri": uri,
        "upload.endpoint_url": s3.endpoint_url, "upload.max_rate": 8 * MB})
    assert recorder.success, recorder
    assert wait_until(lambda: recorder_stats(probe, "/recorder")["current"]["bytes_written"] > 60 * MB, 20.0)
    assert client.unload(recorder.unique_id).success  # finalized; its upload goes on in the container
    big = "first_0.mcap"
    assert wait_until(lambda: journal_rows(tmp_path).get(big, {}).get("parts", 0) >= 2, 20.0), journal_rows(tmp_path)
    process.process.kill()
    process.process.wait()
    # it sees its parent gone within 0.5 s and ends 2 s later at most: longer at nice +10 on a loaded machine
    assert wait_until(lambda: not upload_processes(tmp_path), 15.0), upload_processes(tmp_path)
    before = journal_rows(tmp_path)[big]  # what it confirmed, to the last part it sent
    assert before["state"] == "pending" and before["sent"] < before["size"], before

    if resumer == "recorder":
        process, client = containers.start("--use-intra-process-comms")
        second = client.load("components::Recorder", parameters={
            "storage.uri": str(tmp_path / "second"), "record.topics": ["/nothing"], "upload.uri": uri,
            "upload.endpoint_url": s3.endpoint_url})
        assert second.success, second
        assert wait_until(lambda: recorder_stats(probe, "/recorder")["upload"]["files_pending"] == 0, 30.0), \
            recorder_stats(probe, "/recorder")["upload"]
        assert client.unload(second.unique_id).success
    else:
        done = cli("bag", "upload", "--resume", str(tmp_path), uri, "--endpoint-url", s3.endpoint_url)
        assert done.returncode == 0, done.stderr
        assert "already sent by an earlier attempt" in done.stdout, done.stdout

    after = journal_rows(tmp_path)[big]
    assert after["state"] == "verified", after
    sent_after_restart = after["sent"] - before["sent"]
    assert 0 < sent_after_restart < after["size"] and after["reused"] >= 2 * 8 * (1 << 20), (before, after)
    remote = stored(s3, bucket, "fleet/first/")
    local = {f"fleet/first/{path.name}": path.read_bytes() for path in (tmp_path / "first").iterdir()}
    assert set(remote) == set(local) and all(sha256(remote[k]) == sha256(v) for k, v in local.items())
    # The second recorder's own bag is queued as it is unloaded; the container uploads it in the background.
    assert wait_until(lambda: upload_summary(tmp_path, uri)["complete"], 30.0), upload_summary(tmp_path, uri)
