"""Where component callbacks run: the three executor models of rclcpp's component containers, supervised.

* ``single``: one single-threaded executor, one thread, for every component (``component_container``);
* ``multi``: one multi-threaded executor with ``thread_num`` threads (``component_container_mt``);
* ``isolated``: a single-threaded executor and thread per component (``component_container_isolated``).

rclpy re-raises a callback's exception out of ``spin()``, which would end the thread that runs every other
component too. Here every callback is wrapped where rclpy makes its handler (``Executor._make_handler``, the one
place that knows the entity *and* its node): an exception is handed to ``on_error(node, exc)`` and the thread
goes on. The same wrapper counts each node's in-flight callbacks, so that unloading can *drain* a component
(stop scheduling it, wait for the callbacks already running) before its node is destroyed, and skips callbacks
of a node that is being removed. Anything that still escapes ``spin()`` is an executor failure, reported to
``on_fatal``: the container then shuts down instead of listing components nobody runs.

The container node itself is never spun here: it has its own executor thread so that LoadNode/UnloadNode
answer even while a component callback is busy or blocked.
"""
from __future__ import annotations

import threading
import weakref
from collections import Counter
from typing import Any, Callable, Protocol

from rclpy.context import Context
from rclpy.exceptions import InvalidHandle
from rclpy.executors import Executor, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node

EXECUTOR_KINDS = ("single", "multi", "isolated")
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


class SupervisedExecutor(Executor):
    """An rclpy executor whose callbacks report their exceptions instead of raising out of ``spin()``."""

    def __init__(self, *args: Any, on_error: ErrorHandler | None = None, **kwargs: Any) -> None:
        """``on_error(node, exc)`` gets what a callback of ``node`` raised; without it, it is re-raised."""
        super().__init__(*args, **kwargs)
        self.gate = CallbackGate()
        self._on_error = on_error or _reraise

    def _make_handler(self, entity: Any, node: Node, take_from_wait_list: Callable) -> Any:
        gate, on_error = self.gate, self._on_error

        def supervised_take(entity: Any) -> Callable | None:
            if not gate.enter(node):
                return None  # the node is being unloaded: its pending work is dropped, not run
            try:
                call = take_from_wait_list(entity)
            except COMPONENT_ERRORS as exc:
                gate.leave(node)
                on_error(node, exc)
                return None
            if call is None:
                gate.leave(node)
                return None

            async def supervised_call() -> None:
                try:
                    await call()
                except COMPONENT_ERRORS as exc:
                    on_error(node, exc)
                finally:
                    gate.leave(node)

            return supervised_call

        return super()._make_handler(entity, node, supervised_take)


def _reraise(_node: Node, exc: BaseException) -> None:
    raise exc


class SupervisedSingleThreadedExecutor(SupervisedExecutor, SingleThreadedExecutor):
    """rclpy's SingleThreadedExecutor, supervised."""


class SupervisedMultiThreadedExecutor(SupervisedExecutor, MultiThreadedExecutor):
    """rclpy's MultiThreadedExecutor, supervised."""


class SpinThread:
    """A daemon thread spinning one executor until :meth:`stop`; what escapes ``spin()`` before that goes to
    ``on_fatal`` (without one it is raised). Escapes while stopping are expected and ignored: rclpy's
    MultiThreadedExecutor can raise InvalidHandle from a worker that triggers the guard condition that
    ``shutdown()`` just destroyed."""

    def __init__(self, executor: Executor, name: str, on_fatal: FatalHandler | None = None) -> None:
        self.executor = executor
        self.name = name
        self._on_fatal = on_fatal
        self._stopping = False
        self.thread = threading.Thread(target=self._spin, name=name, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self._spin_through_unloads()
        except BaseException as exc:  # noqa: BLE001 - whatever ends this thread must be reported
            if self._stopping or not self.executor.context.ok():
                return
            if self._on_fatal is None:
                raise
            self._on_fatal(self.name, exc)

    def _spin_through_unloads(self) -> None:
        """rclpy's ``spin()``, except for one race it does not guard against: the executor gathers its wait set
        from a snapshot of its nodes, so a node removed and destroyed on another thread (an unload) in between
        makes ``wait_for_ready_callbacks`` raise InvalidHandle, outside any callback. The next wait set no
        longer holds that node, so the error is transient; only a run of them is a real failure."""
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


class ComponentExecutor(Protocol):
    """What the component manager needs from an executor model."""

    def add(self, node: Node) -> None:
        """Start executing ``node``'s callbacks."""

    def remove(self, node: Node, timeout: float = DRAIN_TIMEOUT) -> bool:
        """Stop executing ``node``'s callbacks and wait up to ``timeout`` s for the running ones (True if
        they finished)."""

    def threads(self) -> list[threading.Thread]:
        """The threads that run component callbacks, for the diagnostics."""

    def shutdown(self, timeout: float = DRAIN_TIMEOUT) -> None:
        """Stop all threads."""


class SharedExecutor:
    """One supervised executor, single- or multi-threaded, shared by every component."""

    def __init__(self, executor: SupervisedExecutor, on_fatal: FatalHandler | None = None) -> None:
        self._executor = executor
        self._spinner = SpinThread(executor, "components", on_fatal)

    def add(self, node: Node) -> None:
        self._executor.add_node(node)

    def remove(self, node: Node, timeout: float = DRAIN_TIMEOUT) -> bool:
        drained = self._executor.gate.close(node, timeout)
        self._executor.remove_node(node)
        return drained

    def threads(self) -> list[threading.Thread]:
        return [self._spinner.thread]

    def shutdown(self, timeout: float = DRAIN_TIMEOUT) -> None:
        self._spinner.stop(timeout)


class IsolatedExecutors:
    """A supervised single-threaded executor and a thread per component."""

    def __init__(self, context: Context, on_error: ErrorHandler | None = None,
                 on_fatal: FatalHandler | None = None) -> None:
        self._context = context
        self._on_error = on_error
        self._on_fatal = on_fatal
        self._running: dict[Node, SpinThread] = {}
        self._lock = threading.Lock()

    def add(self, node: Node) -> None:
        executor = SupervisedSingleThreadedExecutor(context=self._context, on_error=self._on_error)
        executor.add_node(node)
        spinner = SpinThread(executor, f"component:{node.get_name()}", self._on_fatal)
        with self._lock:
            self._running[node] = spinner

    def remove(self, node: Node, timeout: float = DRAIN_TIMEOUT) -> bool:
        with self._lock:
            spinner = self._running.pop(node, None)
        if spinner is None:
            return True
        drained = spinner.executor.gate.close(node, timeout)  # type: ignore[attr-defined]
        spinner.stop(timeout if drained else 0.0)
        return drained

    def threads(self) -> list[threading.Thread]:
        with self._lock:
            return [spinner.thread for spinner in self._running.values()]

    def shutdown(self, timeout: float = DRAIN_TIMEOUT) -> None:
        with self._lock:
            nodes = list(self._running)
        for node in nodes:
            self.remove(node, timeout)


def make_component_executor(kind: str, context: Context, thread_num: int, on_error: ErrorHandler | None = None,
                            on_fatal: FatalHandler | None = None) -> ComponentExecutor:
    """Build the executor model named by ``--executor`` (without handlers, errors propagate as in rclpy)."""
    if kind == "single":
        return SharedExecutor(SupervisedSingleThreadedExecutor(context=context, on_error=on_error), on_fatal)
    if kind == "multi":
        return SharedExecutor(SupervisedMultiThreadedExecutor(num_threads=thread_num, context=context,
                                                              on_error=on_error), on_fatal)
    if kind == "isolated":
        return IsolatedExecutors(context, on_error, on_fatal)
    raise ValueError(f"Unknown executor '{kind}': choose one of {', '.join(EXECUTOR_KINDS)}")
