"""Parameters a load request gave that the component never declared: one warning naming them.

rclpy, like rclcpp, keeps a parameter given at load that the node does not declare as an override nobody reads
(rclcpp_components loads such a component without a word). A misspelled name then silently means the default,
so the container checks every component once its constructor has returned, whatever its class.
"""
from __future__ import annotations

import difflib
from collections.abc import Iterable

from rclpy.node import Node

#: rclpy declares ``qos_overrides.<topic>.<entity>.<policy>`` only when the publisher or subscription they are
#: for is created, which a component may do long after its constructor (a recorder, on discovery).
LATE_DECLARED_PREFIXES = ("qos_overrides.",)


def undeclared_parameters(node: Node, given: Iterable[str]) -> list[str]:
    """The names of ``given`` that ``node`` has not declared, each with the closest declared name if one is near."""
    if getattr(node, "_allow_undeclared_parameters", False):  # the component takes any name on purpose
        return []
    missing = [name for name in dict.fromkeys(given)
               if not node.has_parameter(name) and not name.startswith(LATE_DECLARED_PREFIXES)]
    if not missing:
        return []
    declared = list(node.list_parameters([], 0).names)
    return [_with_suggestion(name, declared) for name in missing]


def warning_text(node_name: str, undeclared: list[str]) -> str:
    """The one warning for ``undeclared`` (from :func:`undeclared_parameters`), as logged and sent to the loader."""
    return (f"{node_name} does not declare the parameter{'s' if len(undeclared) > 1 else ''} "
            f"{', '.join(undeclared)}: ignored")


def _with_suggestion(name: str, declared: list[str]) -> str:
    close = difflib.get_close_matches(name, declared, n=1, cutoff=0.75)
    return f"'{name}' (did you mean '{close[0]}'?)" if close else f"'{name}'"
