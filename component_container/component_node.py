"""The base class for nodes that live in a component container.

A component is an ordinary rclpy ``Node``; deriving from :class:`ComponentNode` adds what the container
provides on top of rclpy, chiefly intra-process publishers and subscriptions.
"""
from __future__ import annotations

from typing import Any

from rclpy.node import Node


class ComponentNode(Node):
    """An rclpy node that a component container can load by plugin name.

    Constructors of components must accept ``node_name`` plus rclpy's ``Node`` keyword arguments
    (``namespace``, ``context``, ``cli_args``, ``use_global_arguments``, ``parameter_overrides`` ...) and pass
    them on, exactly as rclcpp components accept ``rclcpp::NodeOptions``.
    """

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
