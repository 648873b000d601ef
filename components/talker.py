"""``components::Talker``: publishes std_msgs/String "Hello World: N" on ``chatter``, like demo_nodes_cpp."""
from __future__ import annotations

from typing import Any

from std_msgs.msg import String

from component_container.component_node import ComponentNode
from components.sensor_driver import RATE


class Talker(ComponentNode):
    """Publishes a counting greeting at ``rate`` Hz (parameter, default 2.0)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("talker", **kwargs)
        rate = self.declare_parameter("rate", 2.0).value
        RATE.check("'rate'", rate)  # the drivers' bound: a LoadNode request must not set a 1 ns timer
        self.count = 0
        self._publisher = self.create_publisher(String, "chatter", 10)
        self._timer = self.create_timer(1.0 / rate, self._publish)

    def _publish(self) -> None:
        self.count += 1
        self._publisher.publish(String(data=f"Hello World: {self.count}"))
