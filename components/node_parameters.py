"""Declaring a component's rosbag2-style parameters: typed, with errors that name the parameter.

The recorder and the player both take dozens of dotted parameters (``record.*``, ``play.*``, ``storage.*``)
from a LoadNode request. rclpy would accept any value of any type for a parameter declared with dynamic
typing; these helpers turn that into clear errors. (A misspelled name is warned about by the container for
every component: component_container.undeclared_parameters.)
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter

from baglib.format.action_topics import action_topics
from components.qos_profiles import absolute_topic

__all__ = ["clean", "declare_defaults", "given_values", "typed"]


def clean(values: list[str]) -> list[str]:
    """rclpy cannot declare an empty string array without a type, so defaults hold one empty string."""
    return [v for v in values if v]


def given_values(overrides: Mapping[str, Parameter]) -> dict[str, Any]:
    """The parameters a request set; one given as NOT_SET means "use the default"."""
    return {name: p.value for name, p in overrides.items() if p.type_ != Parameter.Type.NOT_SET}


def typed(kind: type, value: Any, label: str) -> Any:
    """``value`` as ``kind`` (the type of the parameter's default), or a ValueError naming the parameter."""
    if kind is list:
        value = [value] if isinstance(value, str) else value
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise ValueError(f"parameter {label} must be a list of strings, got {value!r}")
        return list(value)
    if kind is bool:
        if not isinstance(value, bool):
            raise ValueError(f"parameter {label} must be a boolean, got {value!r}")
        return value
    if kind in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (kind is int and value != int(value)):
            raise ValueError(f"parameter {label} must be a number{' (integer)' if kind is int else ''}, "
                             f"got {value!r}")
        return kind(value)
    if not isinstance(value, str):
        raise ValueError(f"parameter {label} must be a string, got {value!r}")
    return value


def declare_defaults(node: Node, defaults: Mapping[str, Any],
                     kinds: Mapping[str, type] | None = None) -> dict[str, Any]:
    """Declare every parameter of ``defaults`` on ``node``; the typed values (the default where NOT_SET).

    ``kinds`` overrides the type taken from a default (a duration whose default is the integer 0 still
    accepts 2.5 seconds).
    """
    values: dict[str, Any] = {}
    for name, default in defaults.items():
        value = node.declare_parameter(name, default, ParameterDescriptor(dynamic_typing=True)).value
        if value is None:  # declared NOT_SET: show the default that is used
            node.set_parameters([Parameter(name, value=default)])
        kind = (kinds or {}).get(name, type(default))
        values[name] = default if value is None else typed(kind, value, f"'{name}'")
    return values


def action_names(values: list[str], label: str) -> list[str]:
    """record.actions, play.actions_to_filter and their excludes: action names, each checked (an action's own
    topic, such as ``/fibonacci/_action/status``, names no action: rosbag2 would take nothing for it)."""
    names = clean(values)
    for name in names:
        try:
            action_topics(absolute_topic(name))
        except ValueError as error:
            raise ValueError(f"parameter {label}: {error}") from None
    return names
