"""A container's manager in the test process, in a context of its own: for tests where no process boundary is
what is tested (a component's own behaviour, driven and inspected directly)."""
from __future__ import annotations

import contextlib
from typing import Any, Iterator

import rclpy
from rclpy.context import Context

from component_container.component_manager import ComponentManager


@contextlib.contextmanager
def in_process_manager(node_name: str, executor_kind: str = "single", **options: Any) -> Iterator[ComponentManager]:
    """A ComponentManager (``options`` as its constructor's) in a new context; shut down and destroyed after."""
    context = Context()
    rclpy.init(context=context)
    manager = ComponentManager(executor_kind, node_name=node_name, context=context, **options)
    try:
        yield manager
    finally:
        manager.shutdown()
        manager.destroy_node()
        rclpy.try_shutdown(context=context)
