"""rclpy component container: loads nodes by plugin name and connects them intra-process.

``from component_container import ComponentNode`` gives the base class of components (imported on first use,
so that tools importing this package, the CLI among them, do not pay for rclpy's node machinery up front).
"""
from __future__ import annotations

from typing import Any

__all__ = ["ComponentNode"]


def __getattr__(name: str) -> Any:
    if name == "ComponentNode":
        from component_container.component_node import ComponentNode

        return ComponentNode
    raise AttributeError(f"module 'component_container' has no attribute {name!r}")
