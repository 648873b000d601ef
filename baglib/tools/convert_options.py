"""The option files of ``bag convert``, as rosbag2's ``ros2 bag convert`` reads them.

* ``--output-options``: one top-level key ``output_bags``, a list of output bags, each a rosbag2
  ``StorageOptions`` and ``RecordOptions`` in one mapping (rosbag2_py's ``bag_rewrite`` decodes both from the
  same node). ``start_time_ns`` / ``end_time_ns`` keep only the messages with ``start <= log time <= end``
  (Jazzy's ``SequentialWriter``, rosbag2 #1455; a negative value or none: open).
* ``--input-options`` (rosbag2 Lyrical, #2325): one top-level key ``input_bags``, a list of ``uri``,
  ``storage_id`` and the window ``start_time_ns`` / ``end_time_ns`` to read, with the same rule.

A key that is neither is refused, naming it and the bag's position in the list (rosbag2 ignores a misspelled
``stop_time_ns``, and the whole bag is converted; see rosbag2 #1455's discussion). rosbag2 keys that have no
effect on a conversion (:data:`NO_EFFECT`: the cache, discovery, keyboard, the compression threads) are accepted
as they are. Keys this project cannot honour (:data:`UNSUPPORTED`: rosbag2_compression's file and message
compression, another serialization format, a storage plugin configuration file, QoS overrides) are refused when
set to anything but their default; MCAP chunk compression is ``storage_preset_profile: zstd_fast`` or
``zstd_small``.
"""
from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import yaml

__all__ = ["ConvertOptionsError", "InputBag", "NO_EFFECT", "OutputBag", "UNSUPPORTED", "load_input_options",
           "load_output_options"]

#: rosbag2 option keys that change nothing in a conversion.
NO_EFFECT = frozenset({
    "max_cache_size", "snapshot_mode", "is_discovery_disabled", "topic_polling_interval", "node_prefix",
    "include_unpublished_topics", "ignore_leaf_topics", "disable_keyboard_controls", "start_paused",
    "compression_queue_size", "compression_threads", "compression_threads_priority", "use_sim_time",
})
#: rosbag2 option keys refused unless set to one of these values (their defaults).
UNSUPPORTED: dict[str, tuple[Any, ...]] = {
    "compression_mode": ("", "none", None), "compression_format": ("", None),
    "rmw_serialization_format": ("", "cdr", None), "storage_config_uri": ("", None),
    "topic_qos_profile_overrides": ({}, "", None),
}
#: yaml-cpp's ``as<bool>()`` also takes these strings (rosbag2's own example writes ``all_topics: 'true'``).
_TRUE, _FALSE = {"true", "yes", "on", "y"}, {"false", "no", "off", "n"}


class ConvertOptionsError(ValueError):
    """An option file is unreadable or holds something ``bag convert`` does not take; the message names it."""


@dataclass(frozen=True)
class InputBag:
    """One input: a bag directory or single storage file, its storage (``""``: detect) and the window of log
    times read from it (``-1``: open; both ends included)."""

    uri: str
    storage_id: str = ""
    start_time_ns: int = -1
    end_time_ns: int = -1


@dataclass(frozen=True)
class OutputBag:
    """One output bag: where and how it is written, which topics and which log times it takes (rosbag2's
    ``StorageOptions`` and ``RecordOptions`` names; see :mod:`baglib.format.topic_selection` for the topics)."""

    uri: str
    storage_id: str = ""
    max_bagfile_size: int = 0
    max_bagfile_duration: int = 0
    storage_preset_profile: str = ""
    custom_data: dict[str, str] = field(default_factory=dict)
    start_time_ns: int = -1
    end_time_ns: int = -1
    all_topics: bool = False
    all_services: bool = False
    topics: tuple[str, ...] = ()
    topic_types: tuple[str, ...] = ()
    services: tuple[str, ...] = ()
    exclude_topics: tuple[str, ...] = ()
    exclude_topic_types: tuple[str, ...] = ()
    exclude_services: tuple[str, ...] = ()
    all_actions: bool = False
    actions: tuple[str, ...] = ()
    exclude_actions: tuple[str, ...] = ()
    regex: str = ""
    exclude_regex: str = ""
    include_hidden_topics: bool = False


def load_input_options(path: str | os.PathLike[str]) -> list[InputBag]:
    """The ``input_bags`` of the file at ``path``.

    Raises:
        ConvertOptionsError: see module doc; the message names the file, the entry and the key.
    """
    bags = []
    for where, entry in _entries(path, "input_bags"):
        values = _values(where, entry, _INPUT_KEYS)
        bags.append(_windowed(where, InputBag(**values)))
    return bags


def load_output_options(path: str | os.PathLike[str]) -> list[OutputBag]:
    """The ``output_bags`` of the file at ``path``.

    Raises:
        ConvertOptionsError: see module doc; the message names the file, the entry and the key.
    """
    bags = []
    for where, entry in _entries(path, "output_bags"):
        entry = dict(entry)
        if "all" in entry:  # rosbag2: `all` for backward compatibility sets all three
            every = _boolean(f"{where}: all", entry.pop("all"))
            if every:
                entry.setdefault("all_topics", True)
                entry.setdefault("all_services", True)
                entry.setdefault("all_actions", True)
        if "exclude" in entry:  # rosbag2: `exclude` for backward compatibility is `exclude_regex`
            entry.setdefault("exclude_regex", entry.pop("exclude"))
        for key, defaults in UNSUPPORTED.items():
            if key in entry and entry.pop(key) not in defaults:
                raise ConvertOptionsError(f"{where}: {key} is not supported by bag convert here (MCAP chunk "
                                          f"compression is storage_preset_profile: zstd_fast or zstd_small)")
        for key in NO_EFFECT & entry.keys():
            del entry[key]
        bags.append(_windowed(where, OutputBag(**_values(where, entry, _OUTPUT_KEYS))))
    return bags


def _entries(path: str | os.PathLike[str], top: str) -> list[tuple[str, dict[str, Any]]]:
    """The mappings listed under ``top`` in the file, each with its place (``file: top[i]``)."""
    try:
        with open(path, encoding="utf-8") as file:
            document = yaml.safe_load(file)
    except OSError as error:
        raise ConvertOptionsError(f"cannot read {path}: {error.strerror}") from None
    except yaml.YAMLError as error:
        raise ConvertOptionsError(f"{path} is not YAML: {error}") from None
    if not isinstance(document, dict) or top not in document:
        raise ConvertOptionsError(f"{path} must have the top-level key '{top}' (a list of bags)")
    unknown = sorted(str(key) for key in document if key != top)
    if unknown:
        raise ConvertOptionsError(f"{path}: unknown top-level key {', '.join(map(repr, unknown))} (only '{top}')")
    listed = document[top]
    if not isinstance(listed, list) or not listed:
        raise ConvertOptionsError(f"{path}: '{top}' must be a non-empty list of bags")
    entries = []
    for index, entry in enumerate(listed):
        where = f"{path}: {top}[{index}]"
        if not isinstance(entry, dict):
            raise ConvertOptionsError(f"{where} must be a mapping with at least 'uri'")
        entries.append((where, entry))
    return entries


def _values(where: str, entry: dict[str, Any], keys: dict[str, Callable[[str, Any], Any]]) -> dict[str, Any]:
    """The entry's values, each checked by its key's parser; unknown keys and a missing ``uri`` refused."""
    unknown = sorted(str(key) for key in entry if key not in keys)
    if unknown:
        raise ConvertOptionsError(f"{where}: unknown key {', '.join(map(repr, unknown))} (known: "
                                  f"{', '.join(sorted(keys))})")
    if not entry.get("uri"):
        raise ConvertOptionsError(f"{where}: 'uri' is required")
    return {key: keys[key](f"{where}: {key}", value) for key, value in entry.items()}


def _windowed(where: str, bag: Any) -> Any:
    if 0 <= bag.end_time_ns < bag.start_time_ns:
        raise ConvertOptionsError(f"{where}: start_time_ns {bag.start_time_ns} is after end_time_ns "
                                  f"{bag.end_time_ns}")
    return bag


def _text(what: str, value: Any) -> str:
    if value is None:
        return ""
    if not isinstance(value, (str, int, float)) or isinstance(value, bool):
        raise ConvertOptionsError(f"{what} must be a string, not {value!r}")
    return str(value)


def _integer(what: str, value: Any) -> int:
    if isinstance(value, str) and value.strip().lstrip("-").isdigit():
        value = int(value)
    if not isinstance(value, int) or isinstance(value, bool):
        raise ConvertOptionsError(f"{what} must be an integer, not {value!r}")
    return value


def _size(what: str, value: Any) -> int:
    number = _integer(what, value)
    if number < 0:
        raise ConvertOptionsError(f"{what} must not be negative, not {number}")
    return number


def _boolean(what: str, value: Any) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.lower() in _TRUE | _FALSE:
        return value.lower() in _TRUE
    raise ConvertOptionsError(f"{what} must be true or false, not {value!r}")


def _names(what: str, value: Any) -> tuple[str, ...]:
    if value is None:
        return ()
    if not isinstance(value, list) or not all(isinstance(item, str) for item in value):
        raise ConvertOptionsError(f"{what} must be a list of strings, not {value!r}")
    return tuple(item for item in value if item)


def _pairs(what: str, value: Any) -> dict[str, str]:
    """``custom_data``: a mapping, or rosbag2's CLI form, a list of ``key=value``."""
    if value is None:
        return {}
    if isinstance(value, list) and all(isinstance(item, str) and "=" in item for item in value):
        return dict(item.split("=", 1) for item in value)
    if isinstance(value, dict):
        return {str(key): _text(f"{what}.{key}", item) for key, item in value.items()}
    raise ConvertOptionsError(f"{what} must be a mapping of strings (or a list of key=value), not {value!r}")


_INPUT_KEYS: dict[str, Callable[[str, Any], Any]] = {
    "uri": _text, "storage_id": _text, "start_time_ns": _integer, "end_time_ns": _integer,
}
_OUTPUT_KEYS: dict[str, Callable[[str, Any], Any]] = {
    **_INPUT_KEYS, "max_bagfile_size": _size, "max_bagfile_duration": _size, "storage_preset_profile": _text,
    "custom_data": _pairs, "all_topics": _boolean, "all_services": _boolean, "topics": _names,
    "topic_types": _names, "services": _names, "exclude_topics": _names, "exclude_topic_types": _names,
    "exclude_services": _names, "all_actions": _boolean, "actions": _names, "exclude_actions": _names,
    "regex": _text, "exclude_regex": _text, "include_hidden_topics": _boolean,
}
