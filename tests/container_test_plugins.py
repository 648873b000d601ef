"""Components used only by the container tests, loaded as ``tests.container_test_plugins:<Class>`` into a
container started with ``--allow-module-plugins`` and the repository root as its working directory.
"""
from __future__ import annotations

import pathlib
import time
from typing import Any

from rclpy.node import Node
from std_msgs.msg import String


class ThrowingComponent(Node):
    """A component whose constructor raises after the node exists and has a publisher and a timer."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("throwing_component", **kwargs)
        self._publisher = self.create_publisher(String, "thrower_output", 10)
        self._timer = self.create_timer(0.05, lambda: self._publisher.publish(String(data="ghost")))
        raise RuntimeError("deliberate failure in ThrowingComponent.__init__")


class BlockingComponent(Node):
    """A timer callback that blocks: touches ``marker`` (if set) and then sleeps ``block_seconds``."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("blocking_component", **kwargs)
        self.block_seconds = self.declare_parameter("block_seconds", 5.0).value
        self.marker = self.declare_parameter("marker", "").value
        self._timer = self.create_timer(0.05, self._block)

    def _block(self) -> None:
        if self.marker:
            pathlib.Path(self.marker).write_text(str(time.monotonic()))
        time.sleep(self.block_seconds)


class LoggingComponent(Node):
    """Logs one DEBUG and one INFO line per tick, for a few ticks, naming itself."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("logging_component", **kwargs)
        self._ticks = 0
        self._timer = self.create_timer(0.05, self._log)

    def _log(self) -> None:
        self._ticks += 1
        if self._ticks > 3:
            return
        self.get_logger().debug(f"debug-probe from {self.get_name()}")
        self.get_logger().info(f"info-probe from {self.get_name()}")


class NotANode:
    """Not an rclpy Node: the container must refuse to load it."""
