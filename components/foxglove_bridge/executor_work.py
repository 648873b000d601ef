"""Work the SDK's threads hand to the executor, and the answer they wait for.

The SDK calls the bridge's listener on its own threads; rclpy entities (service clients, their calls) are
only touched on the executor that runs the bridge node. A listener callback that needs the ROS graph
(parameters) queues a :class:`Work` and waits, bounded, for its answer; the bridge's housekeeping timer runs
the queue on the executor, where the work starts asynchronous service calls and completes when their
responses arrive.
"""
from __future__ import annotations

import threading
from collections import deque
from typing import Any, Callable


class Work:
    """One request: ``step(work)`` runs on the executor at every tick until it returns True (started).

    What it started calls :meth:`add` with partial results and :meth:`finish` when it has all of them; the
    waiting thread gets whatever was added by then, even after a timeout.
    """

    def __init__(self, step: Callable[["Work"], bool]) -> None:
        self.step = step
        self._results: list[Any] = []
        self._outstanding = 0
        self._done = threading.Event()
        self._lock = threading.Lock()

    def expect(self, count: int = 1) -> None:
        """``count`` more answers are on their way (call before starting them)."""
        with self._lock:
            self._outstanding += count

    def add(self, results: list[Any], answers: int = 1) -> None:
        """Results of ``answers`` of the expected answers (an empty list for a failed call)."""
        with self._lock:
            self._results.extend(results)
            self._outstanding -= answers
            if self._outstanding <= 0:
                self._done.set()

    def finish(self) -> None:
        self._done.set()

    def wait(self, timeout: float) -> list[Any]:
        self._done.wait(timeout)
        with self._lock:
            return list(self._results)


class WorkQueue:
    """Works waiting for the executor; :meth:`run` is called on it."""

    def __init__(self) -> None:
        self._pending: deque[Work] = deque()
        self._lock = threading.Lock()

    def submit(self, step: Callable[[Work], bool], timeout: float) -> list[Any]:
        """Queue ``step`` for the executor and wait at most ``timeout`` seconds for its results."""
        work = Work(step)
        with self._lock:
            self._pending.append(work)
        results = work.wait(timeout)
        with self._lock:
            if work in self._pending:
                self._pending.remove(work)  # never started: the executor must not start it any more
        return results

    def run(self, warn: Callable[[str], None]) -> None:
        """Give every pending work a step; those that started leave the queue."""
        with self._lock:
            pending = list(self._pending)
        for work in pending:
            try:
                started = work.step(work)
            except Exception as exc:  # noqa: BLE001 - a failing request answers with what it has
                warn(f"A client's request failed: {type(exc).__name__}: {exc}")
                started = True
                work.finish()
            if started:
                with self._lock:
                    if work in self._pending:
                        self._pending.remove(work)
