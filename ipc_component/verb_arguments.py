"""The arguments verbs share, checked before any ROS contact so that a typo costs no waiting.

Also where every verb's parser is added (:func:`add_verb`): its one-line summary is both the line in the
parent's list of commands and the start of its own ``-h`` text, so the two cannot drift apart.
"""
from __future__ import annotations

import argparse
import re
from typing import Any, Mapping, Sequence

from ipc_component.ros_session import CliError

LOG_LEVELS = {"DEBUG": 10, "INFO": 20, "WARN": 30, "WARNING": 30, "ERROR": 40, "FATAL": 50}
LOG_LEVEL_HELP = "DEBUG, INFO, WARN, ERROR or FATAL (any case), or 10, 20, 30, 40 or 50"
UINT64_MAX = 2**64 - 1
INT64_MIN, INT64_MAX = -2**63, 2**63 - 1


def parse_log_level(text: str | None) -> int:
    """The rcl_interfaces/msg/Log level for ``--log-level`` (0: not given)."""
    if text is None:
        return 0
    level = LOG_LEVELS.get(text.strip().upper())
    if level is None and text.strip().isdigit() and int(text) in LOG_LEVELS.values():
        level = int(text)
    if level is None:
        raise CliError(f"Invalid log level '{text}': use {LOG_LEVEL_HELP}")
    return level


def parameter_msgs(arguments: Sequence[str] | None, what: str) -> list[Any]:
    """rcl_interfaces/Parameter messages for ``name:=value`` arguments, values typed as YAML."""
    from component_container.parameter_values import parameter_msg, parse_assignment

    messages = []
    for argument in arguments or ():
        try:
            name, value = parse_assignment(argument)
        except ValueError:
            raise CliError(f"Malformed {what} '{argument}': expected name:=value") from None
        integers = value if isinstance(value, list) else [value]
        if any(isinstance(item, int) and not isinstance(item, bool) and not INT64_MIN <= item <= INT64_MAX
               for item in integers):
            raise CliError(f"Invalid {what} '{argument}': integer out of the 64-bit signed range")
        try:
            messages.append(parameter_msg(name, value))
        except Exception as exc:  # noqa: BLE001 - whatever the message types refuse
            raise CliError(f"Invalid {what} '{argument}': {exc or type(exc).__name__}") from None
    return messages


def remap_rules(arguments: Sequence[str] | None) -> list[str]:
    rules = list(arguments or ())
    for rule in rules:
        source, separator, _ = rule.partition(":=")
        if not separator or not source:
            raise CliError(f"Malformed remap rule '{rule}': expected from:=to")
    return rules


def parse_unique_id(text: str) -> int:
    try:
        value = int(text, 10)
    except ValueError:
        value = -1
    if not 0 <= value <= UINT64_MAX:
        raise CliError(f"Invalid component unique id '{text}': expected a non-negative integer")
    return value


def in_options(text: str, options: Mapping[str, str]) -> str:
    """A component's message (``text``) in the words of the command that set its parameters: each parameter in
    ``options`` (parameter -> the option that set it, e.g. ``play.exclude_topics_to_filter`` -> ``--exclude-topics``)
    named as that option. ``parameter 'name'`` and ``'name'`` become the option; ``name:=value`` becomes
    ``option value``. Parameters not in ``options`` (the user typed them with ``-p``) stay as they are."""
    if not options:
        return text
    names = "|".join(re.escape(name) for name in sorted(options, key=len, reverse=True))
    text = re.sub(rf"(?<![\w.])({names}):=", lambda m: f"{options[m[1]]} ", text)
    return re.sub(rf"(?:parameter )?'({names})'|(?<![\w.'])({names})(?![\w.])",
                  lambda m: options[m[1] or m[2]], text)


def add_verb(verbs: Any, name: str, summary: str, details: str = "") -> argparse.ArgumentParser:
    """Add the verb ``name`` to the sub-parsers ``verbs`` and return its parser.

    ``summary`` (one line, no final period) is the verb's line in its parent's list of commands and the first
    sentence of its own ``-h``; ``details`` (sentences) follow it there. Plain text: ``-h`` is read in a
    terminal, so no markup and no source paths.
    """
    description = f"{summary}. {details}".rstrip()
    return verbs.add_parser(name, help=summary, description=description)
