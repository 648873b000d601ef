"""The wait-set executor models keep their wait set between wake-ups (component_container.wait_set_cache): what
changes while they spin must still be seen, and what is destroyed must be forgotten and freed.

Real rclpy nodes over Fast DDS in a context of their own, spun by each wait-set executor model. Each test lets
the executor wait on a built wait set first, then changes it from the test thread, as a load or unload does.
A cache that is not rebuilt on those changes never runs the new entity (or node), and one that keeps the old
handles entered never frees what was destroyed (a DDS reader that stays matched).
"""
from __future__ import annotations

from typing import Iterator

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from test_events_executor import Harness, wait_for

WAIT_SET_KINDS = ("single", "multi", "isolated")


def spun_node(harness: Harness, name: str) -> Node:
    """A node of the harness, added to its executor and ticking a timer (so that its wait set is built)."""
    node = harness.node(name)
    ticks: list[int] = []
    node.create_timer(0.01, lambda: ticks.append(1))
    harness.executor.add(node)
    assert wait_for(lambda: len(ticks) >= 3), f"{name} is not spun"
    return node


@pytest.fixture(params=WAIT_SET_KINDS)
def spinning(request: pytest.FixtureRequest) -> Iterator[Harness]:
    made = Harness(request.param)
    yield made
    made.close()
    assert not made.errors and not made.fatal


def test_entities_created_while_spinning_are_waited_on(spinning: Harness) -> None:
    node = spun_node(spinning, "grows")
    feeder = spinning.node("feeder")
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


def test_destroyed_entities_are_forgotten_and_freed(spinning: Harness) -> None:
    node = spun_node(spinning, "shrinks")
    feeder = spinning.node("feeder")
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


def test_nodes_added_and_removed_while_spinning(spinning: Harness) -> None:
    spun_node(spinning, "stays")
    feeder = spinning.node("feeder")
    publisher = feeder.create_publisher(String, "joined", 10)
    joined = Node("joined", context=spinning.context)  # not the harness's: this test destroys it
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
