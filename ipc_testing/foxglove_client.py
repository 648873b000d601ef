"""Drives Foxglove's own WebSocket client (tests/foxglove_client/client.js, run with the machine's node) from a
test or a benchmark: commands go to its stdin, the events it prints (decoded by Foxglove's ROS 2 CDR reader)
are collected.

:func:`install_client` installs its npm packages once (``npm ci`` from the committed package-lock.json), under
a lock shared by the pytest-xdist workers.
"""
from __future__ import annotations

import fcntl
import json
import pathlib
import re
import shutil
import signal
import subprocess
import threading
from typing import Any, Callable, Sequence

from ipc_testing.calls import wait_until
from ipc_testing.process import stop_process

CLIENT_DIR = pathlib.Path(__file__).resolve().parents[1] / "tests" / "foxglove_client"
URL = re.compile(r"Foxglove bridge listening on (ws://\S+)")


def install_client() -> pathlib.Path:
    """``npm ci`` in tests/foxglove_client unless its node_modules match the lock file; returns the folder."""
    for tool in ("node", "npm"):
        if shutil.which(tool) is None:
            raise AssertionError(f"the Foxglove client tests need {tool} (Node.js 18 or newer) on PATH")
    lock = CLIENT_DIR / "package-lock.json"
    stamp = CLIENT_DIR / "node_modules" / ".installed-lock"
    with open(CLIENT_DIR / ".install.lock", "w") as guard:
        fcntl.flock(guard, fcntl.LOCK_EX)
        if not stamp.exists() or stamp.read_text() != lock.read_text():
            subprocess.run(["npm", "ci", "--no-audit", "--no-fund", "--loglevel=error"], cwd=CLIENT_DIR, check=True,
                           timeout=300)
            stamp.write_text(lock.read_text())
    return CLIENT_DIR


def bridge_url(output: str) -> str:
    """The URL the last bridge loaded into a container logged."""
    urls = URL.findall(output)
    if not urls:
        raise AssertionError(f"no bridge URL in the container's output:\n{output[-3000:]}")
    return urls[-1]


class FoxgloveClient:
    """One ``node client.js URL`` process; its events in :attr:`events`, always stopped by its pid.

    ``subprotocols``: the WebSocket subprotocol names the client offers; by default only
    ``foxglove.websocket.v1``, as ``@foxglove/ws-protocol`` ships (its README's client template).
    """

    def __init__(self, url: str, subprotocols: Sequence[str] = ()) -> None:
        self.url = url
        self.events: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        arguments = [url, ",".join(subprotocols)] if subprotocols else [url]
        self.process = subprocess.Popen(["node", str(CLIENT_DIR / "client.js"), *arguments], stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            try:
                event = json.loads(line)
            except json.JSONDecodeError:
                event = {"event": "output", "text": line.rstrip()}
            with self._lock:
                self.events.append(event)

    def send(self, **command: Any) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write(json.dumps(command) + "\n")
        self.process.stdin.flush()

    def subscribe(self, *topics: str) -> None:
        for topic in topics:
            self.send(op="subscribe", topic=topic)

    def unsubscribe(self, *topics: str) -> None:
        for topic in topics:
            self.send(op="unsubscribe", topic=topic)

    def of(self, kind: str, where: Callable[[dict[str, Any]], bool] = lambda event: True) -> list[dict[str, Any]]:
        """The events of one kind (that satisfy ``where``) received so far."""
        with self._lock:
            return [e for e in self.events if e.get("event") == kind and where(e)]

    def sequences(self, topic: str) -> list[int]:
        """The sequence numbers decoded from the messages of ``topic``, in arrival order."""
        return [int(e["sequence"]) for e in self.of("message", lambda e: e["topic"] == topic)]

    def wait_for(self, kind: str, where: Callable[[dict[str, Any]], bool] = lambda event: True,
                 timeout: float = 20.0) -> dict[str, Any]:
        found = wait_until(lambda: self.of(kind, where), timeout)
        if not found:
            raise AssertionError(f"no {kind} event within {timeout} s; last events: {self.events[-5:]}")
        return found[-1]

    def wait_messages(self, topic: str, count: int, timeout: float = 20.0) -> list[int]:
        """Wait until ``count`` messages of ``topic`` arrived; their sequence numbers."""
        if not wait_until(lambda: len(self.sequences(topic)) >= count, timeout):
            raise AssertionError(f"{len(self.sequences(topic))} of {count} messages of {topic} within {timeout} s; "
                                 f"errors: {self.of('error')}, last events: {self.events[-3:]}")
        return self.sequences(topic)

    def pause(self) -> None:
        """Stop the client process (SIGSTOP): it reads nothing any more and its socket fills up."""
        self.process.send_signal(signal.SIGSTOP)

    def resume(self) -> None:
        self.process.send_signal(signal.SIGCONT)

    def close(self) -> None:
        self.resume()
        stop_process(self.process, signal.SIGTERM, timeout=10.0)
        self._reader.join(timeout=5.0)

    def __enter__(self) -> "FoxgloveClient":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def gaps(sequences: list[int]) -> int:
    """Messages missing between consecutive sequence numbers (0 for a contiguous run)."""
    return sum(b - a - 1 for a, b in zip(sequences, sequences[1:]))
