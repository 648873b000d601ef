"""Service calls and waiting, from a test's or a benchmark's own node.

Every call spins the node in an executor of its own and shuts that executor down (else its finalizer runs after
rclpy's shutdown and prints InvalidHandle at exit).
"""
from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from ipc_component.repeated_call import RepeatedCall
from ipc_testing.fastdds_shm import describe_stranded


def call(node: Node, client: Any, request: Any = None, timeout: float = 20.0, *, again: bool = False) -> Any:
    """Call ``client``'s service and return the response; AssertionError if none comes within ``timeout``.

    ``again``: send the request again until one reply arrives (ipc_component.repeated_call). Fast DDS drops the
    reply to a client whose reply reader the server has not matched yet; only for idempotent requests.
    """
    if request is None:
        request = client.srv_type.Request()
    if not client.wait_for_service(timeout_sec=timeout):
        raise _silence(f"service {client.srv_name} did not appear within {timeout:g} s")
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    deadline = time.monotonic() + timeout
    try:
        if again:
            repeated = RepeatedCall(client, lambda: request)
            try:
                while repeated.reply is None and time.monotonic() < deadline:
                    repeated.step(time.monotonic())
                    executor.spin_once(timeout_sec=0.02)
                reply = repeated.reply
            finally:
                repeated.close()
        else:
            future = client.call_async(request)
            executor.spin_until_future_complete(future, timeout_sec=timeout)
            if not future.done():
                client.remove_pending_request(future)
            reply = future.result() if future.done() else None
    finally:
        executor.remove_node(node)
        executor.shutdown()
    if reply is None:
        raise _silence(f"no reply from {client.srv_name} within {timeout:g} s")
    return reply


def _silence(what: str) -> AssertionError:
    """The failure of a call that heard nothing, with the processes Fast DDS cut off from their shared-memory
    ports, if any (ipc_testing.fastdds_shm): the one cause of silence that nothing else reports."""
    return AssertionError(". ".join(filter(None, [what, describe_stranded()])))


def spin_for(node: Node, seconds: float, until: Callable[[], bool] | None = None) -> bool:
    """Spin ``node`` for ``seconds`` or until ``until()`` holds; returns whether it does (True without one)."""
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    deadline = time.monotonic() + seconds
    try:
        while time.monotonic() < deadline:
            if until is not None and until():
                return True
            executor.spin_once(timeout_sec=0.02)
    finally:
        executor.remove_node(node)
        executor.shutdown()
    return until() if until is not None else True


def wait_until(predicate: Callable[[], Any], timeout: float, node: Node | None = None,
               interval: float = 0.02) -> Any:
    """Poll ``predicate`` (spinning ``node`` meanwhile, if given) until it is truthy or ``timeout`` passes;
    returns its last value."""
    deadline = time.monotonic() + timeout
    while True:
        result = predicate()
        if result or time.monotonic() > deadline:
            return result
        if node is not None:
            rclpy.spin_once(node, timeout_sec=interval)
        else:
            time.sleep(interval)
