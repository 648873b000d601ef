"""``rclpy_components_example::ZeroCopyListener``: receives ``counter`` and shows what zero-copy means.

Loaded with ``use_intra_process_comms`` into the container that runs a CounterPublisher, its callback gets the
very String object the publisher built. Each message names its own object (``... @<id() in hex>``), so the
callback can tell: ``id(msg)`` equal to the named id means "the same object". A copy (the container copies
the first few messages of every publisher while it checks that the publisher does not reuse them: "Ownership
and the reuse rule" in docs/intra-process.md) is made while the original is still alive, so it can never have
that id. Messages from outside the process arrive over DDS and count as copies. (Load both components with
intra-process delivery: without it, the publisher's object may be freed before the listener's DDS copy is made,
and that copy could by chance take the same address.)

Its ``/diagnostics`` status (``health()``) reports ``received``, ``by_reference``, ``copies`` and ``last``.

Parameter ``log_every`` (integer in [0, 100000], can be changed at run time): log every n-th message; 0 logs
nothing.
"""
from __future__ import annotations

import time
from typing import Any

from rcl_interfaces.msg import IntegerRange, ParameterDescriptor
from rclpy.parameter import Parameter
from std_msgs.msg import String

from component_container import ComponentNode
from component_container.health import OK, WARN, Health

#: Seconds without a message after which the status turns to WARN.
QUIET = 5.0


class ZeroCopyListener(ComponentNode):
    """Counts the messages of ``counter`` it received by reference and as copies."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("zero_copy_listener", **kwargs)
        self.log_every = self.declare_parameter("log_every", 0, ParameterDescriptor(
            description="log every n-th message, 0: none (can be changed at run time)",
            integer_range=[IntegerRange(from_value=0, to_value=100_000)])).value
        self.received = 0
        self.by_reference = 0
        self.copies = 0
        self.last = ""
        self._last_received = time.monotonic()
        # In-process when the container loads this node with use_intra_process_comms, plus a DDS reader for
        # publishers in other processes. Called on the container's executor.
        self._subscription = self.create_subscription(String, "counter", self._on_message, 10)
        self.add_post_set_parameters_callback(self._apply)

    def _on_message(self, msg: String) -> None:
        # The message belongs to every subscriber that got it: read it, never change it.
        self.received += 1
        named = msg.data.rpartition(" @")[2]
        if named and named == f"{id(msg):x}":
            self.by_reference += 1
        else:
            self.copies += 1
        self.last = msg.data
        self._last_received = time.monotonic()
        if self.log_every and self.received % self.log_every == 0:
            self.get_logger().info(f"{self.received} received, {self.by_reference} by reference: [{msg.data}]")

    def _apply(self, parameters: list[Parameter]) -> None:
        for parameter in parameters:
            if parameter.name == "log_every":
                self.log_every = parameter.value

    def health(self) -> Health:
        values = {"received": str(self.received), "by_reference": str(self.by_reference),
                  "copies": str(self.copies), "last": self.last}
        if time.monotonic() - self._last_received > QUIET:
            return Health(WARN, f"no message on {self._subscription.topic_name} for {QUIET:g} s", values)
        return Health(OK, f"{self.received} received, {self.by_reference} by reference", values)

    def destroy_node(self) -> None:
        self.get_logger().info(f"{self.received} received, {self.by_reference} by reference, "
                               f"{self.copies} copies")
        super().destroy_node()  # ComponentNode: leaves intra-process delivery, then destroys the node
