"""Where component callbacks run: rclcpp's three component-container executor models and its events one.

* ``single``: one single-threaded executor, one thread, for every component (``component_container``);
* ``multi``: one multi-threaded executor with ``thread_num`` threads (``component_container_mt``);
* ``isolated``: a single-threaded executor and thread per component (``component_container_isolated``);
* ``events``: rclpy's C++ EventsExecutor, one thread, for every component (``component_container_event``);
  opt-in, with the limits its module (component_container.events_executor) documents.

rclpy re-raises a callback's exception out of ``spin()``, which would end the thread that runs every other
component too. In the wait-set models every callback is wrapped where rclpy makes its handler
(``Executor._make_handler``, the one place that knows the entity *and* its node): an exception is handed to
``on_error(node, exc)`` and the thread goes on. The same wrapper counts each node's in-flight callbacks in a
CallbackGate (component_container.callback_supervision), so that unloading can *drain* a component (stop
scheduling it, wait for the callbacks already running) before its node is destroyed, and skips callbacks of a
node that is being removed. Anything that still escapes ``spin()`` is an executor failure, reported to
``on_fatal``: the container then shuts down instead of listing components nobody runs.

The container node itself is never spun here: it has its own executor thread so that LoadNode/UnloadNode
answer even while a component callback is busy or blocked.
"""
from __future__ import annotations

import itertools
import threading
from typing import Any, Callable, Generator, Protocol

from rclpy.callback_groups import CallbackGroup
from rclpy.context import Context
from rclpy.executors import Executor, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.task import Task

from component_container.callback_supervision import (
    COMPONENT_ERRORS,
    DRAIN_TIMEOUT,
    CallbackGate,
    ErrorHandler,
    FatalHandler,
    SpinThread,
    reraise,
)
from component_container.events_executor import EventsSpinThread, SupervisedEventsExecutor
from component_container.intra_process import GuardConditionWakeup, Wakeup
from component_container.wait_set_cache import wait_for_ready_callbacks

EXECUTOR_KINDS = ("single", "multi", "isolated", "events")


class SupervisedExecutor(Executor):
    """An rclpy executor whose callbacks report their exceptions instead of raising out of ``spin()``, and
    whose wait set is rebuilt only when its nodes or their entities change (component_container.wait_set_cache)."""

    def __init__(self, *args: Any, on_error: ErrorHandler | None = None, **kwargs: Any) -> None:
        """``on_error(node, exc)`` gets what a callback of ``node`` raised; without it, it is re-raised."""
        self._changes = itertools.count(1)
        self._generation = 0
        super().__init__(*args, **kwargs)
        self.gate = CallbackGate()
        self._on_error = on_error or reraise

    def wake(self) -> None:
        """rclpy's Node calls this after it created or destroyed an entity: the cached wait set is stale."""
        self._generation = next(self._changes)
        super().wake()

    def add_node(self, node: Node) -> bool:
        added = super().add_node(node)
        if added:
            self.wake()  # after the node is in the set, so that a rebuild cannot miss it
        return added

    def remove_node(self, node: Node) -> None:
        super().remove_node(node)
        self.wake()

    def _wait_for_ready_callbacks(self, timeout_sec: Any = None, nodes: list[Node] | None = None,
                                  condition: Callable[[], bool] = lambda: False
                                  ) -> Generator[tuple[Any, Any, Node], None, None]:
        """Spinning without a timeout over all nodes waits on the cached wait set; anything else is rclpy's."""
        if timeout_sec is None and nodes is None:
            return wait_for_ready_callbacks(self, lambda: self._generation, condition)
        return super()._wait_for_ready_callbacks(timeout_sec, nodes, condition)

    #: Whether handlers run on other threads while this one waits. Then each handler wakes the wait once its
    #: entity is taken and once its callback group is free, so that they are waited on again (rclpy always
    #: does). A single-threaded executor waits only after its handlers ran: there that would be an empty
    #: wake-up per callback.
    HANDLERS_RUN_CONCURRENTLY = True

    def _make_handler(self, entity: Any, node: Node, take_from_wait_list: Callable) -> Task:
        """rclpy's handler, with the callback supervised: counted in the gate, refused for a node being
        removed, and what it raises handed to ``on_error``."""
        gate, on_error, group = self.gate, self._on_error, entity.callback_group
        is_shutdown, work_tracker = self._is_shutdown, self._work_tracker
        guard = self._guard if self.HANDLERS_RUN_CONCURRENTLY else None

        def wake_wait() -> None:
            if guard is not None:
                try:
                    guard.trigger()
                except InvalidHandle:
                    pass  # shutdown() destroyed it: nothing waits any more

        async def supervised() -> None:
            if not gate.enter(node):
                entity._executor_event = False
                return  # the node is being unloaded: its pending work is dropped, not run
            try:
                try:
                    call = take_from_wait_list(entity)
                finally:
                    entity._executor_event = False  # taken: it may be waited on again
                    wake_wait()
                if call is not None:
                    await call()
            except COMPONENT_ERRORS as exc:
                on_error(node, exc)
            finally:
                gate.leave(node)

        async def handler() -> None:
            if is_shutdown or not group.beginning_execution(entity):
                entity._executor_event = False
                wake_wait()
                return
            with work_tracker:
                try:
                    await supervised()
                finally:
                    group.ending_execution(entity)
                    wake_wait()

        entity._executor_event = True  # not waited on until taken
        task = Task(handler, executor=self)
        with self._tasks_lock:
            self._tasks.append((task, entity, node))
        return task

    def make_wakeup(self, node: Node, callback: Callable[[], None], group: CallbackGroup | None) -> Wakeup:
        """A wait-set executor is woken by a guard condition of the node."""
        return GuardConditionWakeup(node, callback, group)


class SupervisedSingleThreadedExecutor(SupervisedExecutor, SingleThreadedExecutor):
    """rclpy's SingleThreadedExecutor, supervised."""

    HANDLERS_RUN_CONCURRENTLY = False


class SupervisedMultiThreadedExecutor(SupervisedExecutor, MultiThreadedExecutor):
    """rclpy's MultiThreadedExecutor, supervised."""


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

    def make_wakeup(self, node: Node, callback: Callable[[], None], group: CallbackGroup | None) -> Wakeup:
        """How the intra-process path makes this executor run ``callback`` for ``node`` (see intra_process)."""


class SharedExecutor:
    """One supervised executor (single-threaded, multi-threaded or events) shared by every component."""

    def __init__(self, executor: SupervisedExecutor | SupervisedEventsExecutor, on_fatal: FatalHandler | None = None,
                 spinner: type[SpinThread] = SpinThread) -> None:
        self._executor = executor
        self._spinner = spinner(executor, "components", on_fatal)
        self.make_wakeup = executor.make_wakeup

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

    @staticmethod
    def make_wakeup(node: Node, callback: Callable[[], None], group: CallbackGroup | None) -> Wakeup:
        return GuardConditionWakeup(node, callback, group)

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
    if kind == "events":
        return SharedExecutor(SupervisedEventsExecutor(context, on_error), on_fatal, EventsSpinThread)
    raise ValueError(f"Unknown executor '{kind}': choose one of {', '.join(EXECUTOR_KINDS)}")
