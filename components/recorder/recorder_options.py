"""The recorder's parameters: rosbag2 Jazzy's ``record.*`` / ``storage.*`` names and defaults, plus the
names the seed tools (humble_ipc_rosbag, rosbag2_composable_recorder) used, accepted as aliases.

| alias (seed tools)                      | rosbag2 parameter              |
|-----------------------------------------|--------------------------------|
| record_all                              | record.all_topics              |
| topic_names, topics                     | record.topics                  |
| exclude                                 | record.exclude_regex           |
| start_paused                            | record.start_paused            |
| start_recording_immediately (inverted)  | record.start_paused            |
| bag_file, bag_name, bag_prefix, uri     | storage.uri                    |
| storage_id                              | storage.storage_id             |
| max_cache_size                          | storage.max_cache_size         |
| max_bag_size, max_bagfile_size          | storage.max_bagfile_size       |
| max_bag_duration, max_bagfile_duration  | storage.max_bagfile_duration   |

An alias given together with its rosbag2 name is an error, so nothing is silently ignored.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter

RECORD_DEFAULTS: dict[str, Any] = {
    "all_topics": False,
    "topics": [""],
    "topic_types": [""],
    "exclude_topics": [""],
    "exclude_topic_types": [""],
    "regex": "",
    "exclude_regex": "",
    "include_hidden_topics": False,
    "include_unpublished_topics": False,
    "topic_polling_interval.sec": 0,
    "topic_polling_interval.nsec": 100_000_000,
    "start_paused": False,
    "qos_profile_overrides_path": "",
    "rmw_serialization_format": "cdr",
}
STORAGE_DEFAULTS: dict[str, Any] = {
    "uri": "",
    "storage_id": "",
    "max_bagfile_size": 0,
    "max_bagfile_duration": 0,
    "max_cache_size": 100 * 1024 * 1024,
    "storage_preset_profile": "",
    "snapshot_mode": False,
    "custom_data": [""],
}
# alias -> (rosbag2 name, converter)
ALIASES: dict[str, tuple[str, Any]] = {
    "record_all": ("record.all_topics", bool),
    "topic_names": ("record.topics", list),
    "topics": ("record.topics", list),
    "exclude": ("record.exclude_regex", str),
    "start_paused": ("record.start_paused", bool),
    "start_recording_immediately": ("record.start_paused", lambda value: not value),
    "bag_file": ("storage.uri", str),
    "bag_name": ("storage.uri", str),
    "bag_prefix": ("storage.uri", str),
    "uri": ("storage.uri", str),
    "storage_id": ("storage.storage_id", str),
    "max_cache_size": ("storage.max_cache_size", int),
    "max_bag_size": ("storage.max_bagfile_size", int),
    "max_bagfile_size": ("storage.max_bagfile_size", int),
    "max_bag_duration": ("storage.max_bagfile_duration", float),
    "max_bagfile_duration": ("storage.max_bagfile_duration", float),
}
STORAGE_IDS = ("mcap", "sqlite3")


@dataclass
class RecordOptions:
    """The recorder's validated settings."""

    all_topics: bool = False
    topics: list[str] = field(default_factory=list)
    topic_types: list[str] = field(default_factory=list)
    exclude_topics: list[str] = field(default_factory=list)
    exclude_topic_types: list[str] = field(default_factory=list)
    regex: str = ""
    exclude_regex: str = ""
    include_hidden_topics: bool = False
    include_unpublished_topics: bool = False
    polling_interval: float = 0.1
    start_paused: bool = False
    qos_profile_overrides_path: str = ""
    uri: str = ""
    storage_id: str = "mcap"
    max_bagfile_size: int = 0
    max_bagfile_duration: float = 0.0
    max_cache_size: int = 100 * 1024 * 1024
    storage_preset_profile: str = ""
    snapshot_mode: bool = False
    custom_data: dict[str, str] = field(default_factory=dict)


def _clean(values: list[str]) -> list[str]:
    """rclpy cannot declare an empty string array without a type, so defaults hold one empty string."""
    return [v for v in values if v]


def declare_options(node: Node, overrides: dict[str, Parameter]) -> RecordOptions:
    """Declare every parameter on ``node`` and return the validated options; ValueError on bad input."""
    values: dict[str, Any] = {}
    for prefix, defaults in (("record", RECORD_DEFAULTS), ("storage", STORAGE_DEFAULTS)):
        for name, default in defaults.items():
            values[f"{prefix}.{name}"] = node.declare_parameter(
                f"{prefix}.{name}", default, ParameterDescriptor(dynamic_typing=True)).value
    for alias, (target, convert) in ALIASES.items():
        given = overrides.get(alias)
        if given is None or alias == target:
            continue
        if target in overrides:
            raise ValueError(f"parameter '{alias}' is an alias of '{target}': give only one of them")
        value = given.value
        if convert is list and isinstance(value, str):
            value = [v.strip() for v in value.replace(",", " ").split()]
        values[target] = convert(value)
        node.declare_parameter(alias, given.value, ParameterDescriptor(dynamic_typing=True))
        # Mirror the value to the rosbag2 name, so `ros2 param get <node> storage.uri` shows what is used.
        node.set_parameters([Parameter(target, value=values[target])])
    return _validate(values)


def _typed(values: dict[str, Any]) -> dict[str, Any]:
    """Coerce each value to its default's type, with an error naming the parameter when impossible."""
    typed = {}
    defaults = {**{f"record.{k}": v for k, v in RECORD_DEFAULTS.items()},
                **{f"storage.{k}": v for k, v in STORAGE_DEFAULTS.items()}}
    for name, value in values.items():
        kind = type(defaults[name])
        if kind is list:
            value = [value] if isinstance(value, str) else value
            if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
                raise ValueError(f"parameter '{name}' must be a list of strings, got {value!r}")
            typed[name] = list(value)
        elif kind is bool:
            if not isinstance(value, bool):
                raise ValueError(f"parameter '{name}' must be a boolean, got {value!r}")
            typed[name] = value
        elif kind is int and name.endswith("duration"):
            typed[name] = _number(name, value, float)
        elif kind in (int, float):
            typed[name] = _number(name, value, kind)
        else:
            typed[name] = str(value)
    return typed


def _number(name: str, value: Any, kind: type) -> Any:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (kind is int and value != int(value)):
        raise ValueError(f"parameter '{name}' must be a number{' (integer)' if kind is int else ''}, "
                         f"got {value!r}")
    return kind(value)


def _validate(values: dict[str, Any]) -> RecordOptions:
    values = _typed(values)
    storage_id = values["storage.storage_id"] or "mcap"
    if storage_id not in STORAGE_IDS:
        raise ValueError(f"parameter 'storage.storage_id' must be one of {', '.join(STORAGE_IDS)}, "
                         f"got '{storage_id}'")
    for name in ("storage.max_bagfile_size", "storage.max_bagfile_duration"):
        if values[name] < 0:
            raise ValueError(f"parameter '{name}' must not be negative, got {values[name]}")
    if values["storage.max_cache_size"] <= 0:
        raise ValueError("parameter 'storage.max_cache_size' must be positive: the recorder needs a cache "
                         f"to hand messages to its writer thread, got {values['storage.max_cache_size']}")
    if values["record.rmw_serialization_format"] != "cdr":
        raise ValueError("parameter 'record.rmw_serialization_format' must be 'cdr'")
    custom: dict[str, str] = {}
    for item in _clean(values["storage.custom_data"]):
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"parameter 'storage.custom_data' entries must be 'key=value', got '{item}'")
        custom[key] = value
    interval = values["record.topic_polling_interval.sec"] + values["record.topic_polling_interval.nsec"] / 1e9
    if interval <= 0:
        raise ValueError("parameter 'record.topic_polling_interval' must be positive")
    return RecordOptions(
        all_topics=values["record.all_topics"],
        topics=_clean(values["record.topics"]),
        topic_types=_clean(values["record.topic_types"]),
        exclude_topics=_clean(values["record.exclude_topics"]),
        exclude_topic_types=_clean(values["record.exclude_topic_types"]),
        regex=values["record.regex"],
        exclude_regex=values["record.exclude_regex"],
        include_hidden_topics=values["record.include_hidden_topics"],
        include_unpublished_topics=values["record.include_unpublished_topics"],
        polling_interval=interval,
        start_paused=values["record.start_paused"],
        qos_profile_overrides_path=values["record.qos_profile_overrides_path"],
        uri=values["storage.uri"],
        storage_id=storage_id,
        max_bagfile_size=int(values["storage.max_bagfile_size"]),
        max_bagfile_duration=float(values["storage.max_bagfile_duration"]),
        max_cache_size=int(values["storage.max_cache_size"]),
        storage_preset_profile=values["storage.storage_preset_profile"],
        snapshot_mode=values["storage.snapshot_mode"],
        custom_data=custom,
    )
