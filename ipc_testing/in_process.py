"""A container's manager in the test process: for tests where no process boundary is what is tested (a component's
own behaviour, driven and inspected directly). Its nodes live in the process's one context
(:mod:`ipc_testing.process_context`), so that no test destroys a participant."""
from __future__ import annotations

import contextlib
import itertools
from typing import Any, Iterator, TypeVar

from rclpy.node import Node
from rclpy.qos import QoSProfile

from component_container.component_manager import ComponentManager
from component_container.component_node import ComponentNode
from ipc_testing.process_context import process_context

N = TypeVar("N", bound=Node)

# The test's own nodes beside each manager's components, destroyed with it: a node left behind stays on the graph
# of the process's later tests (its readers make their publishers write to DDS) under a name they may reuse.
_nodes: dict[int, list[Node]] = {}
_probe_numbers = itertools.count()


@contextlib.contextmanager
def in_process_manager(node_name: str, executor_kind: str = "single", **options: Any) -> Iterator[ComponentManager]:
    """A ComponentManager (``options`` as its constructor's); shut down and destroyed after, with the nodes given
    to :func:`destroyed_with` it."""
    manager = ComponentManager(executor_kind, node_name=node_name, context=process_context(), **options)
    _nodes[id(manager)] = []
    try:
        yield manager
    finally:
        for node in _nodes.pop(id(manager)):
            node.destroy_node()
        manager.shutdown()
        manager.destroy_node()


def destroyed_with(manager: ComponentManager, node: N) -> N:
    """``node`` (in the manager's context), destroyed when :func:`in_process_manager` closes ``manager``."""
    _nodes[id(manager)].append(node)
    return node


class InlineProbe(ComponentNode):
    """Keeps every message of ``topic`` it gets in-process (an inline subscription: no executor needed); made with
    :func:`probe`."""

    def __init__(self, manager: ComponentManager, msg_type: Any, topic: str, qos: QoSProfile) -> None:
        super().__init__(f"probe_{next(_probe_numbers)}", intra_process_manager=manager.intra_process_manager,
                         context=manager.context)
        self.messages: list[Any] = []
        self.create_subscription(msg_type, topic, self.messages.append, qos, intra_process_inline=True)


def probe(manager: ComponentManager, msg_type: Any, topic: str, qos: QoSProfile | None = None) -> InlineProbe:
    """An :class:`InlineProbe` of ``topic`` (``qos`` by default: keep_last 100), destroyed with ``manager``."""
    return destroyed_with(manager, InlineProbe(manager, msg_type, topic, qos or QoSProfile(depth=100)))
