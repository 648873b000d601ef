"""``record start --upload``: every recorder of a fleet session uploads under ``PREFIX/<session>/<host>_<container>/``,
``record status`` shows each one's upload state, and after ``record stop`` the store holds each bag whole. A
container process with the AWS environment of a real nanio server; the commands as users run them."""
from __future__ import annotations

import os
from pathlib import Path

import yaml

from ipc_testing import wait_until
from ipc_testing.process import ContainerProcess
from ipc_testing.s3_server import S3Server
from container_process import REPO
from test_cli import cli
from upload_harness import bucket, s3, sha256, stored  # noqa: F401 - fixtures


def test_a_fleet_session_uploads_each_bag_under_its_session_host_and_container(
        s3: S3Server, bucket: str, tmp_path: Path) -> None:
    load_file = tmp_path / "rig.yaml"
    load_file.write_text(yaml.safe_dump({"components": [
        {"package": "components", "plugin": "components::ImuDriver", "name": "imu", "parameters": {"rate": 50.0}}]}))
    host = os.uname().nodename
    with ContainerProcess("--use-intra-process-comms", "--bag-root", str(tmp_path), "--load", str(load_file),
                          name="/ux/container", cwd=REPO, log_path=tmp_path / "container.log"):
        assert wait_until(lambda: "/imu" in cli("list", "/ux/container").stdout, 60.0)
        refused = cli("record", "start", "/ux/container", "--session", "bad", "--upload", "/mnt/bags")
        assert refused.returncode == 1 and "--upload '/mnt/bags' is not an s3:// URI" in refused.stderr
        started = cli("record", "start", "/ux/container", "--session", "up1", "--in", "0.3", "-p",
                      "storage.max_bagfile_duration:=1", "--upload", f"s3://{bucket}/fleet",
                      "--upload-endpoint-url", s3.endpoint_url)
        assert started.returncode == 0, started.stdout + started.stderr
        prefix = f"fleet/up1/{host}_ux_container/"
        assert wait_until(lambda: stored(s3, bucket, prefix), 20.0)  # a split file, uploaded while recording
        status = cli("record", "status", "--session", "up1")
        assert status.returncode == 0 and status.stdout.splitlines()[0].split()[-1] == "UPLOAD", status.stdout
        assert "complete" in status.stdout or "pending" in status.stdout, status.stdout
        stopped = cli("record", "stop", "--session", "up1", "--in", "0.3")
        assert stopped.returncode == 0, stopped.stdout + stopped.stderr
        bag = tmp_path / "up1" / f"{host}_ux_container"
        local = {prefix + path.name: path.read_bytes() for path in bag.iterdir()}
        assert wait_until(lambda: set(stored(s3, bucket, prefix)) == set(local), 30.0), \
            (sorted(stored(s3, bucket, prefix)), sorted(local))
        remote = stored(s3, bucket, prefix)
        assert all(sha256(remote[key]) == sha256(data) for key, data in local.items())
