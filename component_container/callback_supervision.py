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
        """rclpy's ``spin()``, except for one race it does not guard against: rclpy's executor gathers its wait
        set from a snapshot of its nodes, so a node removed and destroyed on another thread (an unload) in
        between makes ``wait_for_ready_callbacks`` raise InvalidHandle, outside any callback. The cached wait
        set (component_container.wait_set_cache) narrows that to a waitable's own ``add_to_wait_set``. The next
        wait set no longer holds that node, so the error is transient; only a run of them is a real failure."""
        in_a_row = 0
        while self.executor.context.ok() and not self._stopping:
            try:
                self.executor.spin_once()
            except InvalidHandle:
                in_a_row += 1
                if in_a_row > TRANSIENT_INVALID_HANDLES:
                    raise
            else:
                in_a_row = 0

    def stop(self, timeout: float) -> None:
        """Shut the executor down and wait up to ``timeout`` s for the thread."""
        self._stopping = True
        self.executor.shutdown(timeout_sec=timeout)
        self.thread.join(timeout)
