"""``rclpy_components_example::CounterPublisher``: publishes ``"<prefix> <n> @<object id>"`` on ``counter``.

Parameters:

==========  ==========  ==============================================================================
``rate``    10.0        messages per second, a float in [0.1, 100] Hz; can be changed at run time
``prefix``  ``'count'`` first word of every message, 1 to 64 characters; can be changed at run time
==========  ==========  ==============================================================================

Each message ends with ``@`` and the hexadecimal ``id()`` of the message object itself, so that a subscriber
in the same process can tell whether it got the very object published (see ZeroCopyListener).
"""
from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult
from rclpy.parameter import Parameter
from std_msgs.msg import String

from component_container import ComponentNode
from component_container.health import OK, WARN, Health
from components.bounds import Bounds

#: Allowed publishing rates. The load service and the parameter services answer anyone on the ROS domain,
#: so every number they control is bounded (a 1 ns timer would take the whole container down).
RATE = Bounds(0.1, 100.0, "Hz")
#: Allowed length of ``prefix``, in characters.
PREFIX_LENGTH = Bounds(1, 64, "characters")


class CounterPublisher(ComponentNode):
    """Publishes a fresh std_msgs/String ``rate`` times a second."""

    def __init__(self, **kwargs: Any) -> None:
        # kwargs carry what the container passes (context, cli_args, parameter_overrides,
        # intra_process_manager ...): hand them all on.
        super().__init__("counter_publisher", **kwargs)
        try:
            self.rate = self.declare_parameter("rate", 10.0, ParameterDescriptor(
                description=f"messages per second, in {RATE} (can be changed at run time)",
                floating_point_range=[FloatingPointRange(from_value=RATE.minimum, to_value=RATE.maximum)],
            )).value
            self.prefix = self.declare_parameter("prefix", "count", ParameterDescriptor(
                description="first word of every message, 1 to 64 characters (can be changed at run time)",
            )).value
            _check_prefix(self.prefix)  # a load request's value; later changes go through _validate
            self.count = 0
            self._publisher = self.create_publisher(String, "counter", 10)
            self._timer = self.create_timer(1.0 / self.rate, self._tick)
            self.add_on_set_parameters_callback(self._validate)
            self.add_post_set_parameters_callback(self._apply)
        except BaseException:
            self.destroy_node()  # the container reports the exception; leave nothing half-built behind
            raise

    def _tick(self) -> None:
        self.count += 1
        msg = String()  # a new object for every publish: the reference is handed to in-process subscribers
        msg.data = f"{self.prefix} {self.count} @{id(msg):x}"
        self._publisher.publish(msg)
        # Ownership rule: from here on msg belongs to the subscribers. Never change it, never publish it again.

    def _validate(self, parameters: list[Parameter]) -> SetParametersResult:
        """Refuse a bad change with a reason (``ros2 param set`` prints it). rclpy has already checked each
        value's type and the descriptor's range of ``rate``; what a descriptor cannot say is checked here."""
        for parameter in parameters:
            if parameter.name == "prefix":
                try:
                    _check_prefix(parameter.value)
                except ValueError as exc:
                    return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply(self, parameters: list[Parameter]) -> None:
        """Use accepted changes (runs on the executor, like the timer, so no lock is needed)."""
        for parameter in parameters:
            if parameter.name == "prefix":
                self.prefix = parameter.value
            elif parameter.name == "rate":
                self.rate = parameter.value
                self._timer.timer_period_ns = round(1e9 / self.rate)
                self._timer.reset()

    def health(self) -> Health:
        """Shown on /diagnostics about once a second (called from another thread: only reads)."""
        values = {"published": str(self.count), "rate": f"{self.rate:g} Hz", "prefix": self.prefix,
                  "intra_process": str(self.uses_intra_process)}
        if self.count == 0:
            return Health(WARN, "nothing published yet", values)
        return Health(OK, f"published {self.count}", values)

    def destroy_node(self) -> None:
        """Unload: stop the timer first, then let ComponentNode leave intra-process delivery and destroy the
        node (publisher, parameter services) with it."""
        if getattr(self, "_timer", None) is not None:  # also called from a constructor that failed half-way
            self.destroy_timer(self._timer)
            self._timer = None
        super().destroy_node()


def _check_prefix(value: Any) -> None:
    if not isinstance(value, str):
        raise ValueError(f"parameter 'prefix' must be a string, got {value!r}")
    PREFIX_LENGTH.check("'prefix' length", len(value))
