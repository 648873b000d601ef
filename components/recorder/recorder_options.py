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

import re
from dataclasses import dataclass, field
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter

from components.bounds import Bounds
from components.qos_profiles import absolute_topic
from components.image_encoder.image_encoder import DEFAULTS as IMAGE_ENCODER_DEFAULTS
from components.node_parameters import action_names, clean, declare_defaults, given_values, typed
from components.recorder.rate_limits import parse_max_rates
from components.recorder.schedule import duration_ns, instant_ns

#: The ImageEncoder parameters that ``record.compress_<name>`` passes through.
ENCODER_SETTINGS = ("preset", "quality", "bitrate", "keyframe_interval", "width")
RECORD_DEFAULTS: dict[str, Any] = {
    "all_topics": False,
    "all_services": False,
    # rosbag2 Kilted (ros2/rosbag2#1939): actions by name, their feedback, status and service event topics.
    "all_actions": False,
    "actions": [""],
    "exclude_actions": [""],
    "topics": [""],
    "topic_types": [""],
    "services": [""],
    "exclude_topics": [""],
    "exclude_topic_types": [""],
    "exclude_services": [""],
    "regex": "",
    "exclude_regex": "",
    "include_hidden_topics": False,
    "include_unpublished_topics": False,
    "topic_polling_interval.sec": 0,
    "topic_polling_interval.nsec": 100_000_000,
    "start_paused": False,
    "qos_profile_overrides_path": "",
    "rmw_serialization_format": "cdr",
    # rosbag2 Rolling (ros2/rosbag2#2385-#2391): latched messages written again at every split and snapshot;
    # "TOPIC" or "TOPIC=DEPTH" strings, and the depth for every transient_local topic (0: off).
    "repeat_transient_local": [""],
    "repeat_all_transient_local": 0,
    # Not in rosbag2: fleet recording (components/recorder/schedule.py). Instants in seconds since the epoch.
    "start_at": 0.0,
    "stop_at": 0.0,
    "split_at": 0.0,
    "max_duration": 0.0,
    "local_only": False,
    # Not in rosbag2: per-topic rate limits, "PATTERN:RATE" strings (components/recorder/rate_limits.py).
    "max_rates": [""],
    # Not in rosbag2: image topics recorded compressed by an encoder the recorder loads (components/recorder/
    # compression.py); compress_<name> are the encoder's parameters of that name.
    "compress": "",
    "compress_topics": [""],
    "compress_regex": "",
    **{f"compress_{name}": IMAGE_ENCODER_DEFAULTS[name] for name in ENCODER_SETTINGS},
}
STORAGE_DEFAULTS: dict[str, Any] = {
    "uri": "",
    "storage_id": "",
    "max_bagfile_size": 0,
    "max_bagfile_duration": 0,
    "max_cache_size": 100 * 1024 * 1024,
    # rosbag2 Rolling (ros2/rosbag2#2289): the snapshot ring holds at most this many seconds (0: no time bound)
    "max_cache_duration": 0,
    "storage_preset_profile": "",
    "snapshot_mode": False,
    "custom_data": [""],
    # Not in rosbag2: the loss bounds (docs/recorder.md, "Crash and power-loss guarantees").
    "flush_interval": 1.0,
    "sync_interval": 1.0,
    "min_free_space": 256 * 1024 * 1024,
    # rosbag2 Rolling's circular recording (ros2/rosbag2#2218): keep the newest N split files
    "max_bag_files": 0,
    # Not in rosbag2: memory beyond max_cache_size that a writer behind a stalled disk may fill before anything
    # is dropped (-1: a quarter of the available memory, at most STALL_RESERVE_CAP; 0: none, as rosbag2).
    "stall_reserve": -1,
}
DEFAULTS: dict[str, Any] = {**{f"record.{k}": v for k, v in RECORD_DEFAULTS.items()},
                             **{f"storage.{k}": v for k, v in STORAGE_DEFAULTS.items()}}
#: alias -> rosbag2 name; an alias takes the type of its rosbag2 parameter
ALIASES: dict[str, str] = {
    "record_all": "record.all_topics",
    "topic_names": "record.topics",
    "topics": "record.topics",
    "exclude": "record.exclude_regex",
    "start_paused": "record.start_paused",
    "start_recording_immediately": "record.start_paused",
    "bag_file": "storage.uri",
    "bag_name": "storage.uri",
    "bag_prefix": "storage.uri",
    "uri": "storage.uri",
    "storage_id": "storage.storage_id",
    "max_cache_size": "storage.max_cache_size",
    "max_bag_size": "storage.max_bagfile_size",
    "max_bagfile_size": "storage.max_bagfile_size",
    "max_bag_duration": "storage.max_bagfile_duration",
    "max_bagfile_duration": "storage.max_bagfile_duration",
}
#: aliases whose boolean means the opposite of their rosbag2 parameter
INVERTED_ALIASES = frozenset({"start_recording_immediately"})
STORAGE_IDS = ("mcap", "sqlite3")
#: A depth (rosbag2's type) or a boolean (true: depth 1), so it is declared apart from the typed defaults.
REPEAT_ALL = "record.repeat_all_transient_local"
#: Durations take fractions of a second although their rosbag2 defaults are integers.
_KINDS = {"storage.max_bagfile_duration": float, "storage.max_cache_duration": float}

# Bounds of the numbers a LoadNode request sets (see components/bounds.py for why).
#: rosbag2_cpp's writer refuses a split size below its storage plugin's get_minimum_split_file_size(): 86016
#: bytes for sqlite3 (an empty database with rosbag2's schema), 1024 for mcap. Both storages use 86016 here: a
#: 1 KiB limit would still close one file per message and let a request fill the disk with files.
BAGFILE_SIZE = Bounds(86016, 2**63 - 1, "bytes")
#: Shorter files than a second would also mean one file per few messages.
BAGFILE_DURATION = Bounds(1, 365 * 86400, "s")
#: rosbag2's default is 0.1 s; a shorter interval turns discovery into a busy loop on the executor.
POLLING_INTERVAL = Bounds(0.01, 60, "s")
#: storage.flush_interval and storage.sync_interval: 0 switches one off; under 10 ms is a busy disk loop
LOSS_BOUND_INTERVAL = Bounds(0.01, 3600, "s")
MIN_FREE_SPACE = Bounds(1, 2**63 - 1, "bytes")
MAX_BAG_FILES = Bounds(1, 1_000_000, "files")
#: storage.max_cache_duration: rosbag2 takes whole seconds up to 2^32-1; fractions are allowed here
CACHE_DURATION = Bounds(0.001, 2**32 - 1, "s")
#: How many of a topic's last messages record.repeat_transient_local keeps: each is held in memory for good.
REPEAT_DEPTH = Bounds(1, 1000, "messages")
#: The cache may take at most this share of the memory available when the recorder is loaded.
CACHE_MEMORY_SHARE = 0.5
#: storage.stall_reserve -1 (the default) is this share of the available memory ...
STALL_RESERVE_SHARE = 0.25
#: ... at most this many bytes: about 4 s of five 1080p30 cameras.
STALL_RESERVE_CAP = 4 * 1024**3


def memory_available() -> int:
    """Bytes the kernel estimates can be allocated without swapping (MemAvailable of /proc/meminfo)."""
    with open("/proc/meminfo", encoding="ascii") as meminfo:
        for line in meminfo:
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    raise OSError("/proc/meminfo has no MemAvailable line")


def cache_size_bounds() -> Bounds:
    """storage.max_cache_size: at least one byte, at most half of the memory available now."""
    return Bounds(1, int(memory_available() * CACHE_MEMORY_SHARE), "bytes (at most half the available memory)")


def stall_reserve(value: int, label: str) -> int:
    """storage.stall_reserve in bytes: -1 derives it from the memory available now; else 0 up to half of it."""
    if value == -1:
        return min(STALL_RESERVE_CAP, int(memory_available() * STALL_RESERVE_SHARE))
    Bounds(1, int(memory_available() * CACHE_MEMORY_SHARE), "bytes (at most half the available memory)").check(
        label, value, zero_means="drop as soon as max_cache_size is full, as rosbag2 does; -1: automatic")
    return value


@dataclass
class RecordOptions:
    """The recorder's validated settings."""

    all_topics: bool = False
    #: every service whose events are published (introspection enabled), see topic_selection
    all_services: bool = False
    topics: list[str] = field(default_factory=list)
    topic_types: list[str] = field(default_factory=list)
    #: service names (``/add_two_ints``; ``/add_two_ints/_service_event`` is accepted too)
    services: list[str] = field(default_factory=list)
    exclude_topics: list[str] = field(default_factory=list)
    exclude_topic_types: list[str] = field(default_factory=list)
    exclude_services: list[str] = field(default_factory=list)
    #: every action (its five topics, see baglib.format.action_topics)
    all_actions: bool = False
    #: action names (``/fibonacci``)
    actions: list[str] = field(default_factory=list)
    exclude_actions: list[str] = field(default_factory=list)
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
    #: seconds (by receive time) the snapshot ring holds at most, besides max_cache_size (0: no time bound)
    max_cache_duration: float = 0.0
    #: bytes beyond max_cache_size that a writer behind a stalled disk may fill before anything is dropped
    stall_reserve: int = 0
    storage_preset_profile: str = ""
    snapshot_mode: bool = False
    custom_data: dict[str, str] = field(default_factory=dict)
    #: seconds after which a received message is a complete record in the file (0: chunks close by size only)
    flush_interval: float = 1.0
    #: seconds between fsyncs of the current file (0: only when a file is closed)
    sync_interval: float = 1.0
    #: bytes to keep free on the bag's disk: below it the recorder stops (bag finalized) or refuses to start
    min_free_space: int = 256 * 1024 * 1024
    #: keep only the newest N split files (0: all)
    max_bag_files: int = 0
    #: the scheduled window (ns since the epoch, 0: none; see components/recorder/schedule.py)
    start_ns: int = 0
    stop_ns: int = 0
    split_ns: int = 0
    max_duration_ns: int = 0
    #: record only what publishers of this container publish (in-process), never the same topic from elsewhere
    local_only: bool = False
    #: topic -> how many of its last messages are written again at the start of every split file and snapshot
    repeat_transient_local: dict[str, int] = field(default_factory=dict)
    #: that depth for every topic recorded with transient_local durability (0: only the topics named above)
    repeat_all_transient_local: int = 0
    #: per-topic rate limits, validated ``"PATTERN:RATE"`` strings (see components/recorder/rate_limits.py)
    max_rates: list[str] = field(default_factory=list)
    #: record.compress: the codec image topics are recorded in ("": raw), which topics, and the encoder's settings
    compress: str = ""
    compress_topics: list[str] = field(default_factory=list)
    compress_regex: str = ""
    compress_settings: dict[str, Any] = field(default_factory=dict)


def declare_options(node: Node, overrides: dict[str, Parameter]) -> RecordOptions:
    """Declare every parameter on ``node`` and return the validated options; ValueError on bad input.

    Errors name the parameter as the user gave it (an alias, or the rosbag2 name); a parameter given as
    NOT_SET means its default. An alias is declared when given, so the container's warning about undeclared
    parameters (component_container.undeclared_parameters) names only what the recorder does not know.
    """
    given = given_values(overrides)
    values = declare_defaults(node, {k: v for k, v in DEFAULTS.items() if k != REPEAT_ALL}, _KINDS)
    declared = node.declare_parameter(REPEAT_ALL, DEFAULTS[REPEAT_ALL], ParameterDescriptor(dynamic_typing=True))
    values[REPEAT_ALL] = DEFAULTS[REPEAT_ALL] if declared.value is None else declared.value
    sources = {name: name for name in DEFAULTS}  # rosbag2 name -> the name the user gave it as
    for alias, target in ALIASES.items():
        if alias not in given:
            continue
        if target in given:
            raise ValueError(f"parameter '{alias}' is an alias of '{target}': give only one of them")
        value = given[alias]
        if isinstance(DEFAULTS[target], list) and isinstance(value, str):  # the seed tools took "a, b" for a list
            value = [v.strip() for v in value.replace(",", " ").split()]
        sources[target] = alias
        value = typed(_KINDS.get(target, type(DEFAULTS[target])), value, _label(target, alias))
        values[target] = not value if alias in INVERTED_ALIASES else value
        node.declare_parameter(alias, given[alias], ParameterDescriptor(dynamic_typing=True))
        # Mirror the value to the rosbag2 name, so `ros2 param get <node> storage.uri` shows what is used.
        node.set_parameters([Parameter(target, value=values[target])])
    return _validate(values, {name: _label(name, source) for name, source in sources.items()})


def repeat_depths(items: list[str], label: str) -> dict[str, int]:
    """``record.repeat_transient_local``'s ``TOPIC`` / ``TOPIC=DEPTH`` strings (rosbag2's format, depth 1 when
    omitted) as absolute topic name -> depth; ValueError naming the parameter on a bad entry."""
    depths: dict[str, int] = {}
    for item in clean(items):
        topic, separator, depth = item.strip().partition("=")
        depth = depth if separator else "1"
        if not topic:
            raise ValueError(f"parameter {label} entries must be 'TOPIC' or 'TOPIC=DEPTH', got '{item}'")
        try:
            count = int(depth)
        except ValueError:
            raise ValueError(f"parameter {label}: the depth of '{item}' must be an integer") from None
        REPEAT_DEPTH.check(f"{label} ('{topic}')", count)
        depths[absolute_topic(topic)] = count
    return depths


def repeat_all_depth(value: Any, label: str) -> int:
    """``record.repeat_all_transient_local``: rosbag2's depth (0: off); ``true`` / ``false`` mean 1 / 0."""
    if isinstance(value, bool):
        return int(value)
    if not isinstance(value, int):
        raise ValueError(f"parameter {label} must be a boolean or a depth (integer), got {value!r}")
    REPEAT_DEPTH.check(label, value, zero_means="off")
    return value


def custom_data_pairs(items: list[str]) -> dict[str, str]:
    """``storage.custom_data``'s ``key=value`` strings as a map (rosbag2's format); ValueError on a bad entry."""
    pairs: dict[str, str] = {}
    for item in clean(items):
        key, separator, value = item.partition("=")
        if not separator or not key:
            raise ValueError(f"parameter 'storage.custom_data' entries must be 'key=value', got '{item}'")
        pairs[key] = value
    return pairs


def _label(name: str, source: str) -> str:
    """How an error names a parameter: as the user gave it."""
    return f"'{name}'" if source == name else f"'{source}' (alias of '{name}')"


def _validate(values: dict[str, Any], labels: dict[str, str]) -> RecordOptions:
    storage_id = values["storage.storage_id"] or "mcap"
    if storage_id not in STORAGE_IDS:
        raise ValueError(f"parameter {labels['storage.storage_id']} must be one of {', '.join(STORAGE_IDS)}, "
                         f"got '{storage_id}'")
    BAGFILE_SIZE.check(labels["storage.max_bagfile_size"], values["storage.max_bagfile_size"],
                       zero_means="no splitting")
    BAGFILE_DURATION.check(labels["storage.max_bagfile_duration"], values["storage.max_bagfile_duration"],
                           zero_means="no splitting")
    cache_size_bounds().check(labels["storage.max_cache_size"], values["storage.max_cache_size"])
    for name in ("storage.flush_interval", "storage.sync_interval"):
        LOSS_BOUND_INTERVAL.check(labels[name], values[name], zero_means="off")
    MIN_FREE_SPACE.check(labels["storage.min_free_space"], values["storage.min_free_space"], zero_means="no guard")
    MAX_BAG_FILES.check(labels["storage.max_bag_files"], values["storage.max_bag_files"], zero_means="keep all")
    if values["storage.max_bag_files"] and not (values["storage.max_bagfile_size"]
                                                 or values["storage.max_bagfile_duration"]):
        raise ValueError(f"parameter {labels['storage.max_bag_files']} needs splitting: set "
                         "storage.max_bagfile_size or storage.max_bagfile_duration too")
    if values["record.rmw_serialization_format"] != "cdr":
        raise ValueError("parameter 'record.rmw_serialization_format' must be 'cdr'")
    custom = custom_data_pairs(values["storage.custom_data"])
    CACHE_DURATION.check(labels["storage.max_cache_duration"], values["storage.max_cache_duration"],
                         zero_means="no time bound")
    for name in ("record.regex", "record.exclude_regex", "record.compress_regex"):
        try:
            re.compile(values[name])
        except re.error as exc:
            raise ValueError(f"parameter {labels[name]} is not a valid regular expression: {exc}") from None
    max_rates = clean(values["record.max_rates"])
    parse_max_rates(max_rates, labels["record.max_rates"])
    interval = values["record.topic_polling_interval.sec"] + values["record.topic_polling_interval.nsec"] / 1e9
    POLLING_INTERVAL.check("'record.topic_polling_interval' (.sec + .nsec)", interval)
    return RecordOptions(
        all_topics=values["record.all_topics"],
        all_services=values["record.all_services"],
        topics=clean(values["record.topics"]),
        topic_types=clean(values["record.topic_types"]),
        services=clean(values["record.services"]),
        exclude_topics=clean(values["record.exclude_topics"]),
        exclude_topic_types=clean(values["record.exclude_topic_types"]),
        exclude_services=clean(values["record.exclude_services"]),
        all_actions=values["record.all_actions"],
        actions=action_names(values["record.actions"], labels["record.actions"]),
        exclude_actions=action_names(values["record.exclude_actions"], labels["record.exclude_actions"]),
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
        max_cache_duration=float(values["storage.max_cache_duration"]),
        stall_reserve=stall_reserve(int(values["storage.stall_reserve"]), labels["storage.stall_reserve"]),
        storage_preset_profile=values["storage.storage_preset_profile"],
        snapshot_mode=values["storage.snapshot_mode"],
        custom_data=custom,
        flush_interval=float(values["storage.flush_interval"]),
        sync_interval=float(values["storage.sync_interval"]),
        min_free_space=int(values["storage.min_free_space"]),
        max_bag_files=int(values["storage.max_bag_files"]),
        start_ns=instant_ns("record.start_at", float(values["record.start_at"])),
        stop_ns=instant_ns("record.stop_at", float(values["record.stop_at"])),
        split_ns=instant_ns("record.split_at", float(values["record.split_at"])),
        max_duration_ns=duration_ns("record.max_duration", float(values["record.max_duration"])),
        local_only=values["record.local_only"],
        max_rates=max_rates,
        repeat_transient_local=repeat_depths(values["record.repeat_transient_local"],
                                             labels["record.repeat_transient_local"]),
        repeat_all_transient_local=repeat_all_depth(values[REPEAT_ALL], labels[REPEAT_ALL]),
        compress=values["record.compress"].strip().lower(),
        compress_topics=clean(values["record.compress_topics"]),
        compress_regex=values["record.compress_regex"],
        compress_settings={name: values[f"record.compress_{name}"] for name in ENCODER_SETTINGS},
    )
