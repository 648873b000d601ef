"""Allowed ranges of the numbers that a LoadNode request or a parameter change controls.

The container's load service and every node's parameter services answer anyone on the ROS domain, so each
number they accept is attack surface: a cache of 10^18 bytes, a 1 ns polling timer or a 1 GiB camera frame at
10 kHz would take the whole container down. The recorder and the sensor drivers check such numbers with one
:class:`Bounds` each, so every refusal reads the same way and names the parameter and its allowed range.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


def _number(value: float) -> str:
    """A bound or value as users type it: integers in full, whole floats without a point, others short."""
    if isinstance(value, int):
        return str(value)
    return str(int(value)) if value.is_integer() and abs(value) < 1e15 else f"{value:g}"


@dataclass(frozen=True)
class Bounds:
    """A closed range ``[minimum, maximum]`` in ``unit`` for one numeric parameter."""

    minimum: float
    maximum: float
    unit: str = ""

    def __str__(self) -> str:
        return f"[{_number(self.minimum)}, {_number(self.maximum)}]" + (f" {self.unit}" if self.unit else "")

    def contains(self, value: float) -> bool:
        return math.isfinite(value) and self.minimum <= value <= self.maximum

    def check(self, label: str, value: Any, *, zero_means: str = "") -> None:
        """Raise ValueError naming the parameter (``label``, already quoted) unless ``value`` is a number in range.

        ``zero_means``: 0 is also accepted, as the switch-off value it documents (e.g. "no splitting").
        """
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"parameter {label} must be a number, got {value!r}")
        if zero_means and value == 0:
            return
        if not self.contains(value):
            allowed = f"0 ({zero_means}) or in {self}" if zero_means else f"in {self}"
            raise ValueError(f"parameter {label} must be {allowed}, got {value!r}")
