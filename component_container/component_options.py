"""Turning a LoadNode request into the arguments a component's constructor receives.

This mirrors ``ComponentManager::create_node_options`` of rclcpp_components: global arguments off, the
request's parameters as overrides, remap rules plus ``__node``/``__ns`` as the node's own ``--ros-args``,
and the two boolean extra arguments type-checked with rclcpp's error text.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import ParameterType
from rclpy.logging import LoggingSeverity
from rclpy.parameter import Parameter

# rcl_interfaces/msg/Log levels; 0 leaves the component's logger as it is.
LOG_LEVELS = {0, 10, 20, 30, 40, 50}
BOOLEAN_EXTRA_ARGUMENTS = ("use_intra_process_comms", "forward_global_arguments")


class LoadRequestError(Exception):
    """The request itself is invalid; the message goes back to the caller and no id is used up."""


@dataclass
class ComponentOptions:
    """Everything the container needs to construct and configure one component."""

    node_kwargs: dict[str, Any]
    use_intra_process_comms: bool
    log_level: LoggingSeverity | None


def options_from_request(request: Any, default_intra_process: bool) -> ComponentOptions:
    """Validate a ``composition_interfaces/srv/LoadNode`` request and build the component's options."""
    extra = {p.name: p.value for p in request.extra_arguments}
    flags = {}
    for name in BOOLEAN_EXTRA_ARGUMENTS:
        value = extra.get(name)
        if value is not None and value.type != ParameterType.PARAMETER_BOOL:
            raise LoadRequestError(f"Extra component argument '{name}' must be a boolean")
        flags[name] = value.bool_value if value is not None else None
    if request.log_level not in LOG_LEVELS:
        raise LoadRequestError(
            f"Invalid log_level {request.log_level}: use 10 (DEBUG), 20 (INFO), 30 (WARN), 40 (ERROR), "
            "50 (FATAL) or 0 to keep the default")
    try:
        parameters = [Parameter.from_parameter_msg(p) for p in request.parameters]
    except Exception as exc:  # a malformed ParameterValue from a hand-written client
        raise LoadRequestError(f"Invalid parameter in request: {exc}") from exc

    cli_args = ["--ros-args"]
    for rule in request.remap_rules:
        cli_args += ["-r", rule]
    if request.node_name:
        cli_args += ["-r", f"__node:={request.node_name}"]
    if request.node_namespace:
        cli_args += ["-r", f"__ns:={request.node_namespace}"]
    intra_process = flags["use_intra_process_comms"]
    return ComponentOptions(
        node_kwargs={
            "cli_args": cli_args,
            "use_global_arguments": bool(flags["forward_global_arguments"]),
            "parameter_overrides": parameters,
        },
        use_intra_process_comms=default_intra_process if intra_process is None else intra_process,
        log_level=LoggingSeverity(request.log_level) if request.log_level else None,
    )

