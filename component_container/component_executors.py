"""Where component callbacks run: the three executor models of rclcpp's component containers.

* ``single``: one single-threaded executor, one thread, for every component (``component_container``);
* ``multi``: one multi-threaded executor with ``thread_num`` threads (``component_container_mt``);
* ``isolated``: a single-threaded executor and thread per component (``component_container_isolated``).

The container node itself is never spun here: it has its own executor thread so that LoadNode/UnloadNode
answer even while a component callback is busy or blocked.
"""
from __future__ import annotations

import threading
from typing import Protocol

from rclpy.context import Context
from rclpy.executors import Executor, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node

EXECUTOR_KINDS = ("single", "multi", "isolated")
# How long unloading waits for a component's in-flight callbacks before destroying it anyway.
CALLBACK_DRAIN_TIMEOUT = 5.0


def spin_in_thread(executor: Executor, name: str) -> threading.Thread:
    """Spin ``executor`` on a daemon thread until it is shut down."""

    def spin() -> None:
        try:
            executor.spin()
        except Exception:  # a context shut down under the executor ends the thread quietly
            if executor.context.ok():
                raise

    thread = threading.Thread(target=spin, name=name, daemon=True)
    thread.start()
    return thread


class ComponentExecutor(Protocol):
    """What the component manager needs from an executor model."""

    def add(self, node: Node) -> None:
        """Start executing ``node``'s callbacks."""

    def remove(self, node: Node) -> None:
        """Stop executing ``node``'s callbacks (in-flight ones may still be finishing)."""

    def shutdown(self) -> None:
        """Stop all threads."""


class SharedExecutor:
    """One executor, single- or multi-threaded, shared by every component."""

    def __init__(self, executor: Executor) -> None:
        self._executor = executor
        self._thread = spin_in_thread(executor, "components")

    def add(self, node: Node) -> None:
        self._executor.add_node(node)

    def remove(self, node: Node) -> None:
        self._executor.remove_node(node)

    def shutdown(self) -> None:
        self._executor.shutdown(timeout_sec=CALLBACK_DRAIN_TIMEOUT)
        self._thread.join(timeout=CALLBACK_DRAIN_TIMEOUT)


class IsolatedExecutors:
    """A single-threaded executor and a thread per component; removing one cancels and joins it."""

    def __init__(self, context: Context) -> None:
        self._context = context
        self._running: dict[Node, tuple[SingleThreadedExecutor, threading.Thread]] = {}
        self._lock = threading.Lock()

    def add(self, node: Node) -> None:
        executor = SingleThreadedExecutor(context=self._context)
        executor.add_node(node)
        with self._lock:
            self._running[node] = (executor, spin_in_thread(executor, f"component:{node.get_name()}"))

    def remove(self, node: Node) -> None:
        with self._lock:
            executor, thread = self._running.pop(node, (None, None))
        if executor is not None and thread is not None:
            executor.shutdown(timeout_sec=CALLBACK_DRAIN_TIMEOUT)
            thread.join(timeout=CALLBACK_DRAIN_TIMEOUT)

    def shutdown(self) -> None:
        with self._lock:
            nodes = list(self._running)
        for node in nodes:
            self.remove(node)


def make_component_executor(kind: str, context: Context, thread_num: int) -> ComponentExecutor:
    """Build the executor model named by ``--executor``."""
    if kind == "single":
        return SharedExecutor(SingleThreadedExecutor(context=context))
    if kind == "multi":
        return SharedExecutor(MultiThreadedExecutor(num_threads=thread_num, context=context))
    if kind == "isolated":
        return IsolatedExecutors(context)
    raise ValueError(f"Unknown executor '{kind}': choose one of {', '.join(EXECUTOR_KINDS)}")
