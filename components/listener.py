"""``components::Listener``: logs every std_msgs/String it receives on ``chatter``."""
from __future__ import annotations

from typing import Any

from std_msgs.msg import String

from component_container.component_node import ComponentNode


class Listener(ComponentNode):
    """Subscribes to ``chatter`` and logs "I heard: [...]"."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("listener", **kwargs)
        self.received_count = 0
        self.last_message: String | None = None
        self._subscription = self.create_subscription(String, "chatter", self._on_message, 10)

    def _on_message(self, msg: String) -> None:
        self.received_count += 1
        self.last_message = msg
        self.get_logger().info(f"I heard: [{msg.data}]")
