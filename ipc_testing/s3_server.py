"""A real S3-compatible server process on loopback for tests and benchmarks: nanio (SigV4, multipart with
ListParts), or localbucket as a second implementation of what it supports. Never a mock of the client.

The server's credentials are test-only values, handed to the code under test through the standard AWS
environment variables (:meth:`S3Server.env`); ``AWS_CONFIG_FILE`` and ``AWS_SHARED_CREDENTIALS_FILE`` point
nowhere, so a developer's own ``~/.aws`` is never read. The server can be killed and started again on the same
port and data (a server restart in the middle of an upload).
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from ipc_testing.process import stop_process

ACCESS_KEY = "ipc-test-access"
SECRET_KEY = "ipc-test-secret-key"


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class S3Server:
    """``kind`` ("nanio" or "localbucket") serving ``data_dir`` on 127.0.0.1; a context manager. ``secret_key``:
    the account's secret (another than :meth:`env` gives: a store that refuses the client's credentials)."""

    def __init__(self, data_dir: Path, kind: str = "nanio", log: Path | None = None,
                 secret_key: str = SECRET_KEY) -> None:
        self.data_dir = data_dir
        self.kind = kind
        self.secret_key = secret_key
        self.port = _free_port()
        self.log = log or data_dir.with_suffix(".log")
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def endpoint_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def env(self) -> dict[str, str]:
        """The AWS environment that reaches this server's account (and no file of the user's)."""
        return {"AWS_ACCESS_KEY_ID": ACCESS_KEY, "AWS_SECRET_ACCESS_KEY": SECRET_KEY,
                "AWS_DEFAULT_REGION": "us-east-1", "AWS_CONFIG_FILE": os.devnull,
                "AWS_SHARED_CREDENTIALS_FILE": os.devnull}

    def start(self) -> S3Server:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        bin_dir = Path(sys.executable).parent
        if self.kind == "nanio":
            command = [str(bin_dir / "nanio"), "serve", "--host", "127.0.0.1", "--port", str(self.port),
                       "--data-dir", str(self.data_dir)]
        else:
            command = [str(bin_dir / "localbucket"), str(self.data_dir), "--port", str(self.port)]
        env = {**os.environ, "NANIO_ACCESS_KEY": ACCESS_KEY, "NANIO_SECRET_KEY": self.secret_key}
        with open(self.log, "ab") as log:
            self.process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"{self.kind} exited at start: {self.log.read_text()[-2000:]}")
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return self
            except OSError:
                time.sleep(0.05)
        raise RuntimeError(f"{self.kind} did not listen on port {self.port} within 20 s")

    def kill(self) -> None:
        """SIGKILL the server (a crash: no request in flight is answered)."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()

    def pause(self) -> None:
        """SIGSTOP the server: connections are accepted by the kernel, nothing is answered (a stalled store)."""
        assert self.process is not None
        self.process.send_signal(signal.SIGSTOP)

    def resume(self) -> None:
        assert self.process is not None
        self.process.send_signal(signal.SIGCONT)

    def stop(self) -> None:
        if self.process is not None:
            stop_process(self.process, timeout=5.0)

    def __enter__(self) -> S3Server:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def client(self) -> Any:
        """A boto3 client of this server, for the tests' own checks (not the code under test's)."""
        import boto3
        from botocore.config import Config
        return boto3.client("s3", endpoint_url=self.endpoint_url, aws_access_key_id=ACCESS_KEY,
                            aws_secret_access_key=SECRET_KEY, region_name="us-east-1",
                            config=Config(s3={"addressing_style": "path"},
                                          request_checksum_calculation="when_required",
                                          response_checksum_validation="when_required"))

    def requests(self) -> list[str]:
        """The request lines of nanio's access log so far (``"PUT /bucket/key?... HTTP/1.1" 200``)."""
        return [line for line in self.log.read_text(errors="replace").splitlines() if '"' in line and "HTTP/" in line]
