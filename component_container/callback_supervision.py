"""The supervision primitives every executor model shares: the per-node callback gate and the spinning thread.

A component's callback runs *supervised*: what it raises is handed to ``on_error(node, exc)`` (the container
delists and unloads or exits) instead of ending the thread that runs the other components, and it is counted
in the :class:`CallbackGate`, so that unloading can *drain* a component (admit no new callbacks of its node,
wait for the running ones) before the node is destroyed. Where the wrapping happens depends on the executor
(component_executors: rclpy's ``Executor._make_handler``; events_executor: the entities' callback objects);
these two pieces do not.
"""
from __future__ import annotations

import threading
import time
import weakref
from collections import Counter
from typing import Any, Callable

from rclpy.exceptions import InvalidHandle
from rclpy.node import Node

#: What a component callback may raise and still be handled as that component's failure (SystemExit too:
#: a component calling sys.exit() must not end a thread that runs other components).
COMPONENT_ERRORS = (Exception, SystemExit)

ErrorHandler = Callable[[Node, BaseException], None]
FatalHandler = Callable[[str, BaseException], None]
#: How long removing a node waits for its running callbacks unless the caller says otherwise.
DRAIN_TIMEOUT = 5.0
#: How often stopping a spinning thread wakes it again while it has not left.
WAKE_INTERVAL = 0.05
#: InvalidHandle errors in a row, from the executor's own wait-set code, that still count as unload races.
TRANSIENT_INVALID_HANDLES = 100


class CallbackGate:
    """Which nodes may run callbacks, and how many of their callbacks are running right now."""

    def __init__(self) -> None:
        # Weak: a removed node stays refused for as long as a stale handler could still name it, no longer.
        self._closed: weakref.WeakSet[Node] = weakref.WeakSet()
        self._running: Counter[Node] = Counter()
        self._idle = threading.Condition()

    def enter(self, node: Node | None) -> bool:
        """Start one callback of ``node``; False (do not run it) if the node is being removed."""
        with self._idle:
            if node in self._closed:
                return False
            self._running[node] += 1
            return True

    def leave(self, node: Node | None) -> None:
        with self._idle:
            self._running[node] -= 1
            if self._running[node] <= 0:
                del self._running[node]
                self._idle.notify_all()

    def close(self, node: Node, timeout: float) -> bool:
        """Admit no more callbacks of ``node`` and wait for the running ones; False if they did not finish."""
        with self._idle:
            self._closed.add(node)
            return self._idle.wait_for(lambda: self._running[node] <= 0, timeout)


def reraise(_node: Node, exc: BaseException) -> None:
    """The error handler of an executor built without one: rclpy's own behaviour."""
    raise exc


class SpinThread:
    """A daemon thread spinning one executor until :meth:`stop`; what escapes ``spin()`` before that goes to
    ``on_fatal`` (without one it is raised). Escapes while stopping are expected and ignored: rclpy's
    MultiThreadedExecutor can raise InvalidHandle from a worker that triggers the guard condition that
    ``shutdown()`` just destroyed."""

    def __init__(self, executor: Any, name: str, on_fatal: FatalHandler | None = None) -> None:
        self.executor = executor
        self.name = name
        self._on_fatal = on_fatal
        self._stopping = False
        self.thread = threading.Thread(target=self._spin, name=name, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.run_executor()
        except BaseException as exc:  # noqa: BLE001 - whatever ends this thread must be reported
            if self._stopping or not self.executor.context.ok():
                return
            if self._on_fatal is None:
                raise
            self._on_fatal(self.name, exc)

    def run_executor(self) -> None:
        """rclpy's ``spin()``, with two differences.

        * A wake-up that finds the thread told to stop ends the wait (``spin_once()`` itself goes back to
          waiting when a wake-up brings no work): one call of rclpy's ``spin_until_future_complete`` loop, with
          :meth:`_stop_requested` as its condition.
        * One race rclpy does not guard against: the executor gathers its wait set from a snapshot of its
          nodes, so a node removed and destroyed on another thread (an unload) in between makes
          ``wait_for_ready_callbacks`` raise InvalidHandle, outside any callback. The cached wait set
          (component_container.wait_set_cache) narrows that to a waitable's own ``add_to_wait_set``. The next
          wait set no longer holds that node, so the error is transient; only a run of them is a real failure."""
        in_a_row = 0
        while self.executor.context.ok() and not self._stopping:
            try:
                self.executor._spin_once_impl(None, self._stop_requested)
            except InvalidHandle:
                in_a_row += 1
                if in_a_row > TRANSIENT_INVALID_HANDLES:
                    raise
            else:
                in_a_row = 0

    def _stop_requested(self) -> bool:
        return self._stopping

    def stop(self, timeout: float) -> None:
        """Stop the thread, then shut the executor down; ``timeout`` s at most in all.

        The thread is told to stop and woken (again every ``WAKE_INTERVAL``, in case it was inside a callback)
        while the executor still runs, and the executor is shut down only once the thread has left, or when the
        time is up (a callback that never returns). Shutting rclpy's executor down first strands the thread:
        ``shutdown()`` destroys the guard condition that wakes the wait set, so a thread that had gathered its
        next wait set (the guard taken, not yet entered) waits without it, forever if no entity of its nodes
        becomes ready, with every one of their handles in use while the nodes are destroyed. A wake-up of the
        live guard condition is kept until a wait takes it, so it cannot be lost that way."""
        self._stopping = True
        deadline = time.monotonic() + timeout
        while True:
            self.interrupt()
            self.thread.join(max(0.0, min(WAKE_INTERVAL, deadline - time.monotonic())))
            if not self.thread.is_alive() or time.monotonic() >= deadline:
                break
        self.executor.shutdown(timeout_sec=max(0.0, deadline - time.monotonic()))
        self.thread.join(max(0.0, deadline - time.monotonic()))

    def interrupt(self) -> None:
        """Make the spinning thread return to its loop (where it sees ``_stopping``) soon."""
        self.executor.wake()
