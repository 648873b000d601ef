"""A container's manager in the test process: for tests where no process boundary is what is tested (a component's
own behaviour, driven and inspected directly). Its nodes live in the process's one context
(:mod:`ipc_testing.process_context`), so that no test destroys a participant."""
from __future__ import annotations

import contextlib
from typing import Any, Iterator

from component_container.component_manager import ComponentManager
from ipc_testing.process_context import process_context


@contextlib.contextmanager
def in_process_manager(node_name: str, executor_kind: str = "single", **options: Any) -> Iterator[ComponentManager]:
    """A ComponentManager (``options`` as its constructor's); shut down and destroyed after."""
    manager = ComponentManager(executor_kind, node_name=node_name, context=process_context(), **options)
    try:
        yield manager
    finally:
        manager.shutdown()
        manager.destroy_node()
