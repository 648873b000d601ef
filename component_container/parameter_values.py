"""``name:=value`` arguments typed the way ``ros2 component`` and ``ros2 param`` type them.

The value is parsed as YAML: booleans, integers, floats and strings keep their type, a list whose items
all share one of those types becomes the matching array, anything else is passed on as a string.
"""
from __future__ import annotations

from typing import Any

import yaml
from rcl_interfaces.msg import Parameter as ParameterMsg
from rclpy.parameter import Parameter

_SCALARS = (bool, int, float, str)


def typed_value(text: str) -> Any:
    """The Python value ``ros2 component`` would send for ``text``."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    if value is None:
        return text
    if isinstance(value, _SCALARS):
        return value
    if isinstance(value, list) and value:
        kinds = {type(item) for item in value}
        if len(kinds) == 1 and kinds.pop() in _SCALARS:
            return value
    return text


def parse_assignment(argument: str) -> tuple[str, Any]:
    """Split ``name:=value`` on the first ``:=`` and type the value; ValueError if there is no ``:=``."""
    name, separator, text = argument.partition(":=")
    if not separator or not name:
        raise ValueError(f"Malformed argument '{argument}': expected name:=value")
    return name, typed_value(text)


def parameter_msg(name: str, value: Any) -> ParameterMsg:
    """An ``rcl_interfaces/Parameter`` message carrying ``value`` with its ROS type."""
    return Parameter(name, value=value).to_parameter_msg()
