"""The upload processes of this container: one per journal (per directory of bags), shared by its recorders.

A recorder with ``upload.uri`` takes the process of its journal (starting it if there is none or it exited) and
wakes it when a file is queued. A recorder that is unloaded releases it; the last release closes the process's
input, which tells it to finish what is queued and exit, so uploads outlive the recorder but not the work. At the
container's exit every process still running is told to stop (SIGTERM: it stops between two requests, the
journal keeps the rest) and is waited for by its pid.
"""
from __future__ import annotations

import atexit
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

#: Seconds an upload process may take to stop between two requests at the container's exit.
STOP_TIMEOUT = 5.0


@dataclass
class _Worker:
    process: subprocess.Popen[bytes]
    max_rate: float
    users: int = 0


_lock = threading.Lock()
_workers: dict[Path, _Worker] = {}


def _start(journal: Path, max_rate: float) -> _Worker:
    process = subprocess.Popen([sys.executable, "-m", "baglib.upload.worker", str(journal),
                                "--max-rate", str(max_rate)], stdin=subprocess.PIPE, close_fds=True)
    return _Worker(process, max_rate)


def acquire(journal: Path, max_rate: float) -> None:
    """Use the upload process of ``journal``; one is started if none is running or it is finishing."""
    with _lock:
        worker = _workers.get(journal)
        if worker is None or worker.process.poll() is not None or worker.process.stdin is None or \
                worker.process.stdin.closed:
            worker = _workers[journal] = _start(journal, max_rate)
        worker.users += 1


def wake(journal: Path) -> None:
    """Tell the process of ``journal`` that something was queued (restarting it if it died)."""
    with _lock:
        worker = _workers.get(journal)
        if worker is None:
            return
        if worker.process.poll() is not None:
            users = worker.users
            worker = _workers[journal] = _start(journal, worker.max_rate)
            worker.users = users
        try:
            assert worker.process.stdin is not None
            worker.process.stdin.write(b"\n")
            worker.process.stdin.flush()
        except (BrokenPipeError, ValueError):
            pass  # it is exiting: the next acquire or wake starts another, which finds the queue in the journal


def release(journal: Path) -> None:
    """One user less; the last one closes the input: the process finishes the queue, then exits."""
    with _lock:
        worker = _workers.get(journal)
        if worker is None:
            return
        worker.users -= 1
        if worker.users <= 0 and worker.process.stdin is not None and not worker.process.stdin.closed:
            try:
                worker.process.stdin.close()
            except BrokenPipeError:
                pass


def running(journal: Path) -> bool:
    """Whether an upload process of ``journal`` is still at work (maybe finishing after its last release)."""
    with _lock:
        worker = _workers.get(journal)
        return worker is not None and worker.process.poll() is None


def stop(journal: Path | None = None) -> None:
    """The upload process of ``journal`` (None: every one; at exit) stops between two requests, the journal
    keeping the rest, and is reaped."""
    with _lock:
        workers = [worker for path, worker in _workers.items() if journal is None or path == journal]
        for path in [path for path in _workers if journal is None or path == journal]:
            del _workers[path]
    for worker in workers:
        if worker.process.poll() is None:
            worker.process.terminate()
    for worker in workers:
        try:
            worker.process.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            worker.process.kill()
            worker.process.wait()


atexit.register(stop)
