"""The wait-set executor models keep their wait set between wake-ups (component_container.wait_set_cache): what
changes while they spin must still be seen, and what is destroyed must be forgotten and freed.

Real rclpy nodes over Fast DDS in a context of their own, spun by each wait-set executor model. Each test lets
the executor wait on a built wait set first, then changes it from the test thread, as a load or unload does.
A cache that is not rebuilt on those changes never runs the new entity (or node), and one that keeps the old
handles entered never frees what was destroyed (a DDS reader that stays matched).
"""
from __future__ import annotations

import time
from typing import Any, Callable, Iterator

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from component_container.component_executors import ComponentExecutor, make_component_executor

WAIT_SET_KINDS = ("single", "multi", "isolated")


class Spinning:
    """An executor model spinning in its own context, with the errors it reports."""

    def __init__(self, kind: str) -> None:
        self.context = Context()
        rclpy.init(context=self.context)
        self.errors: list[BaseException] = []
        self.executor: ComponentExecutor = make_component_executor(
            kind, self.context, 2, lambda _node, exc: self.errors.append(exc),
            lambda _name, exc: self.errors.append(exc))
        self.nodes: list[Node] = []

    def node(self, name: str, spun: bool = True) -> Node:
        """A node of this context, added to the executor once it ticks a timer (so its wait set is built)."""
        node = Node(name, context=self.context)
        self.nodes.append(node)
        if spun:
            ticks: list[int] = []
            node.create_timer(0.01, lambda: ticks.append(1))
            self.executor.add(node)
            assert wait_for(lambda: len(ticks) >= 3), f"{name} is not spun"
        return node

    def close(self) -> None:
        for node in self.nodes:
            self.executor.remove(node, 1.0)
            node.destroy_node()
        self.executor.shutdown(2.0)
        rclpy.try_shutdown(context=self.context)


@pytest.fixture(params=WAIT_SET_KINDS)
def spinning(request: pytest.FixtureRequest) -> Iterator[Spinning]:
    made = Spinning(request.param)
    yield made
    made.close()
    assert not made.errors


def wait_for(condition: Callable[[], Any], timeout: float = 10.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if result := condition():
            return result
        time.sleep(0.01)
    return condition()


def test_entities_created_while_spinning_are_waited_on(spinning: Spinning) -> None:
    node = spinning.node("grows")
    feeder = spinning.node("feeder", spun=False)
    publisher = feeder.create_publisher(String, "grown", 10)
    received: list[str] = []
    node.create_subscription(String, "grown", lambda msg: received.append(msg.data), 10)
    fired: list[int] = []
    node.create_timer(0.01, lambda: fired.append(1))
    guarded: list[int] = []
    guard = node.create_guard_condition(lambda: guarded.append(1))
    guard.trigger()
    node.create_service(Trigger, "grown_service", lambda _req, resp: resp)

    assert wait_for(lambda: fired and guarded), (fired, guarded)
    assert wait_for(lambda: publisher.get_subscription_count() == 1)
    assert wait_for(lambda: publisher.publish(String(data="late")) or received)
    client = feeder.create_client(Trigger, "grown_service")
    assert client.wait_for_service(timeout_sec=10.0)
    caller = SingleThreadedExecutor(context=spinning.context)  # the feeder is not spun by the one under test
    caller.add_node(feeder)
    future = client.call_async(Trigger.Request())
    caller.spin_until_future_complete(future, timeout_sec=10.0)
    caller.shutdown()
    assert future.result() is not None, "the service created while spinning did not answer"


def test_destroyed_entities_are_forgotten_and_freed(spinning: Spinning) -> None:
    node = spinning.node("shrinks")
    feeder = spinning.node("feeder", spun=False)
    publisher = feeder.create_publisher(String, "shrunk", 10)
    received: list[str] = []
    subscription = node.create_subscription(String, "shrunk", lambda msg: received.append(msg.data), 10)
    assert wait_for(lambda: publisher.get_subscription_count() == 1)
    assert wait_for(lambda: publisher.publish(String(data="before")) or received)

    ticks: list[int] = []
    timer = node.create_timer(0.01, lambda: ticks.append(1))
    assert wait_for(lambda: ticks)
    node.destroy_subscription(subscription)
    node.destroy_timer(timer)
    # The executor released the handles: the DDS reader is gone, not kept alive by a stale wait set.
    assert wait_for(lambda: publisher.get_subscription_count() == 0), "the destroyed subscription is still matched"
    count, seen = len(ticks), len(received)
    publisher.publish(String(data="after"))
    later: list[int] = []
    node.create_timer(0.01, lambda: later.append(1))
    assert wait_for(lambda: len(later) >= 5)  # the executor runs on, and more than long enough passed
    assert len(ticks) == count and len(received) == seen


def test_nodes_added_and_removed_while_spinning(spinning: Spinning) -> None:
    spinning.node("stays")
    feeder = spinning.node("feeder", spun=False)
    publisher = feeder.create_publisher(String, "joined", 10)
    joined = Node("joined", context=spinning.context)
    received: list[str] = []
    joined.create_subscription(String, "joined", lambda msg: received.append(msg.data), 10)
    ticks: list[int] = []
    joined.create_timer(0.01, lambda: ticks.append(1))
    spinning.executor.add(joined)
    assert wait_for(lambda: ticks)
    assert wait_for(lambda: publisher.publish(String(data="hello")) or received)

    assert spinning.executor.remove(joined, 2.0)
    count = len(ticks)
    joined.destroy_node()
    assert wait_for(lambda: publisher.get_subscription_count() == 0), "the removed node's reader is still matched"
    assert len(ticks) == count
    stays_ticks: list[int] = []
    spinning.nodes[0].create_timer(0.01, lambda: stays_ticks.append(1))
    assert wait_for(lambda: len(stays_ticks) >= 3)  # the other node is still spun
