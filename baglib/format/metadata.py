"""The bag's description: topics, files and the ``metadata.yaml`` (version 9) that ties them together.

Readers trust ``metadata.yaml`` more than the storage files: ``rosbags`` only reads a topic whose
name, type, serialization format and offered QoS profiles equal the storage's entry, and only the
files listed here. So one module owns both the YAML document and the QoS text the storage plugins
embed, which keeps the two representations identical by construction.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

if TYPE_CHECKING:
    from rclpy.qos import QoSProfile

__all__ = [
    "METADATA_FILENAME",
    "METADATA_VERSION",
    "QOS_KEYS",
    "ROS_DISTRO",
    "SAFE_LOADER",
    "BagMetadata",
    "FileInfo",
    "TopicInfo",
    "fsync_directory",
    "normalize_type",
    "parse_qos_profiles",
    "qos_profile_dict",
    "serialize_qos_profiles",
]

METADATA_FILENAME = "metadata.yaml"
#: The Jazzy format: QoS enums as strings and offered_qos_profiles as a YAML list.
METADATA_VERSION = 9
ROS_DISTRO = "jazzy"

#: Every QoS profile needs all nine keys, in rosbag2's order, or readers drop the topic.
QOS_KEYS = (
    "history",
    "depth",
    "reliability",
    "durability",
    "deadline",
    "lifespan",
    "liveliness",
    "liveliness_lease_duration",
    "avoid_ros_namespace_conventions",
)

_NS_PER_S = 1_000_000_000
#: RMW_DURATION_INFINITE, {sec: 9223372036, nsec: 854775807} once split.
_INFINITE_NS = 2**63 - 1
# Foxy-era middlewares reported "infinite" as ~2**31 s; rosbag2 maps those to RMW_DURATION_INFINITE
# on playback, so anything this long is recorded as infinite right away.
_LEGACY_INFINITE_NS = 0x7FFFFFFF * _NS_PER_S


def _duration_dict(nanoseconds: int) -> dict[str, int]:
    if nanoseconds >= _LEGACY_INFINITE_NS:
        nanoseconds = _INFINITE_NS
    return {"sec": nanoseconds // _NS_PER_S, "nsec": nanoseconds % _NS_PER_S}


def qos_profile_dict(qos: QoSProfile) -> dict[str, Any]:
    """Convert an rclpy QoS profile (e.g. from a publisher's endpoint info) to rosbag2's form.

    Policies become rmw's strings (``keep_last``, ``best_effort``, ``transient_local`` ...),
    durations ``{sec, nsec}``; an infinite duration becomes ``{sec: 9223372036, nsec: 854775807}``.
    """
    return {
        "history": qos.history.name.lower(),
        "depth": int(qos.depth),
        "reliability": qos.reliability.name.lower(),
        "durability": qos.durability.name.lower(),
        "deadline": _duration_dict(qos.deadline.nanoseconds),
        "lifespan": _duration_dict(qos.lifespan.nanoseconds),
        "liveliness": qos.liveliness.name.lower(),
        "liveliness_lease_duration": _duration_dict(qos.liveliness_lease_duration.nanoseconds),
        "avoid_ros_namespace_conventions": bool(qos.avoid_ros_namespace_conventions),
    }


#: libyaml's emitter when PyYAML has it: a split writes this document three times (the closing file's record,
#: the next file's opening record, metadata.yaml), slowly enough with the pure-Python emitter to stall the bag
#: writer on every split; libyaml is about ten times faster. Its block lists are not indented under their key
#: (yaml-cpp's are): the same document to any YAML reader, rosbag2's included.
_BaseDumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


class _Dumper(_BaseDumper):  # type: ignore[valid-type, misc]
    """Block-style YAML with rosbag2's ``~`` for null."""


_Dumper.add_representer(
    type(None), lambda dumper, _: dumper.represent_scalar("tag:yaml.org,2002:null", "~")
)


#: libyaml's safe loader when PyYAML has it: a bag holds a QoS document per topic and file.
SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _dump(document: Any) -> str:
    return yaml.dump(
        document, Dumper=_Dumper, sort_keys=False, default_flow_style=False,
        allow_unicode=True, width=2**30,
    )


def serialize_qos_profiles(profiles: list[dict[str, Any]]) -> str:
    """The QoS list as the YAML *string* that MCAP channel metadata and sqlite3 topic rows hold."""
    return _dump(profiles)


# The policies as rmw numbers them (rmw/types.h); metadata before version 9 and Humble-era storage
# files store these integers. A number rmw has no string for (Foxy's deprecated manual_by_node)
# reads as "unknown", as rosbag2's own conversion gives.
_POLICY_NAMES: dict[str, tuple[str, ...]] = {
    "history": ("system_default", "keep_last", "keep_all", "unknown"),
    "reliability": ("system_default", "reliable", "best_effort", "unknown", "best_available"),
    "durability": ("system_default", "transient_local", "volatile", "unknown", "best_available"),
    "liveliness": ("system_default", "automatic", "unknown", "manual_by_topic", "unknown", "best_available"),
}
_DURATION_KEYS = ("deadline", "lifespan", "liveliness_lease_duration")


def parse_qos_profiles(stored: Any) -> list[dict[str, Any]]:
    """The offered QoS profiles as any rosbag2 version stored them, in :func:`qos_profile_dict`'s form.

    ``stored`` is the YAML list itself (metadata version 9) or the YAML *text* of it (older
    metadata, MCAP channel metadata, sqlite3 topic rows); ``""`` or ``None`` means none recorded.
    Policies may be rmw's integers (before version 9) or strings; Foxy's "infinite" durations
    become ``{sec: 9223372036, nsec: 854775807}``, as rosbag2's ``qos.cpp`` reads them.

    Raises:
        ValueError: not YAML, not a list of profiles, or a profile lacking one of :data:`QOS_KEYS`.
    """
    if isinstance(stored, str):
        try:
            stored = yaml.load(stored, Loader=SAFE_LOADER) if stored.strip() else None  # noqa: S506 (safe)
        except yaml.YAMLError as error:
            raise ValueError(f"offered_qos_profiles is not YAML ({error})") from error
    if stored is None:
        return []
    if not isinstance(stored, list) or not all(isinstance(profile, dict) for profile in stored):
        raise ValueError("offered_qos_profiles is not a list of QoS profiles")
    return [_parse_qos_profile(profile) for profile in stored]


def _parse_qos_profile(stored: dict[str, Any]) -> dict[str, Any]:
    missing = [key for key in QOS_KEYS if key not in stored]
    if missing:
        raise ValueError(f"a QoS profile lacks {', '.join(missing)}")
    try:
        profile: dict[str, Any] = {}
        for key in QOS_KEYS:
            value = stored[key]
            if key in _POLICY_NAMES:
                names = _POLICY_NAMES[key]
                if isinstance(value, bool) or not isinstance(value, (int, str)):
                    raise ValueError(f"{key} {value!r} is not a policy")
                if isinstance(value, int):
                    value = names[value] if 0 <= value < len(names) else "unknown"
                else:
                    value = value.lower() if value.lower() in names else "unknown"
            elif key in _DURATION_KEYS:
                value = _duration_dict(int(value["sec"]) * _NS_PER_S + int(value["nsec"]))
            elif key == "depth":
                value = int(value)
            else:
                value = bool(value)
            profile[key] = value
    except (KeyError, TypeError) as error:
        raise ValueError(f"a QoS profile has an invalid value ({error!r})") from error
    return profile


def normalize_type(type_name: str) -> str:
    """``pkg/Type`` -> ``pkg/msg/Type``: readers match topics on the three-part spelling only."""
    parts = type_name.split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and all(parts):
        return type_name
    raise ValueError(f"not a ROS type name (expected 'pkg/msg/Type'): {type_name!r}")


@dataclass
class TopicInfo:
    """One recorded topic as rosbag2 describes it (``TopicMetadata``).

    ``offered_qos_profiles`` are the publishers' offers (see :func:`qos_profile_dict`), each with
    all of :data:`QOS_KEYS`. ``type_description_hash`` is ``RIHS01_<sha256 hex>``; leaving it empty
    lets the bag writer fill in the locally installed type's hash.
    """

    name: str
    type: str
    serialization_format: str = "cdr"
    offered_qos_profiles: list[dict[str, Any]] = field(default_factory=list)
    type_description_hash: str = ""

    def __post_init__(self) -> None:
        if not self.name.startswith("/"):
            raise ValueError(f"topic name must be fully qualified (start with '/'): {self.name!r}")
        self.type = normalize_type(self.type)
        for profile in self.offered_qos_profiles:
            missing = [key for key in QOS_KEYS if key not in profile]
            if missing:
                raise ValueError(f"QoS profile of {self.name} lacks {', '.join(missing)}")

    def to_dict(self) -> dict[str, Any]:
        """The ``topic_metadata`` entry of ``metadata.yaml``."""
        return {
            "name": self.name,
            "type": self.type,
            "serialization_format": self.serialization_format,
            "offered_qos_profiles": [
                {key: profile[key] for key in QOS_KEYS} for profile in self.offered_qos_profiles
            ],
            "type_description_hash": self.type_description_hash,
        }


@dataclass
class FileInfo:
    """What one storage file holds; ``path`` is relative to the bag directory.

    ``topic_message_counts`` is not written into the file's ``files`` entry; the bag sums it into
    ``topics_with_message_count``.
    """

    path: str
    starting_time_ns: int = 0
    duration_ns: int = 0
    message_count: int = 0
    topic_message_counts: dict[str, int] = field(default_factory=dict)

    @classmethod
    def from_log_times(
        cls, path: str, first_ns: int | None, last_ns: int | None, topic_message_counts: dict[str, int]
    ) -> FileInfo:
        """Build the entry from the earliest and latest log time (``None`` when empty)."""
        counts = {topic: count for topic, count in topic_message_counts.items() if count}
        if first_ns is None or last_ns is None:
            return cls(path, 0, 0, 0, counts)
        return cls(path, first_ns, last_ns - first_ns, sum(counts.values()), counts)

    def to_dict(self) -> dict[str, Any]:
        """The ``files`` entry of ``metadata.yaml``."""
        return {
            "path": self.path,
            "starting_time": {"nanoseconds_since_epoch": self.starting_time_ns},
            "duration": {"nanoseconds": self.duration_ns},
            "message_count": self.message_count,
        }


@dataclass
class BagMetadata:
    """The whole bag: every topic (with or without messages) and every file, in order."""

    storage_identifier: str
    topics: list[TopicInfo] = field(default_factory=list)
    files: list[FileInfo] = field(default_factory=list)
    custom_data: dict[str, str] | None = None

    @property
    def message_count(self) -> int:
        return sum(info.message_count for info in self.files)

    @property
    def starting_time_ns(self) -> int:
        """Earliest log time in the bag (0 for a bag without messages)."""
        starts = [info.starting_time_ns for info in self.files if info.message_count]
        return min(starts, default=0)

    @property
    def duration_ns(self) -> int:
        """Latest minus earliest log time."""
        ends = [info.starting_time_ns + info.duration_ns for info in self.files if info.message_count]
        return max(ends) - self.starting_time_ns if ends else 0

    def topic_message_counts(self) -> dict[str, int]:
        """Messages per topic over all files; every known topic is present, possibly with 0."""
        counts = {topic.name: 0 for topic in self.topics}
        for info in self.files:
            for name, count in info.topic_message_counts.items():
                counts[name] = counts.get(name, 0) + count
        return counts

    def to_dict(self) -> dict[str, Any]:
        """The ``rosbag2_bagfile_information`` document, keys in rosbag2's order."""
        counts = self.topic_message_counts()
        return {
            "version": METADATA_VERSION,
            "storage_identifier": self.storage_identifier,
            "duration": {"nanoseconds": self.duration_ns},
            "starting_time": {"nanoseconds_since_epoch": self.starting_time_ns},
            "message_count": self.message_count,
            "topics_with_message_count": [
                {"topic_metadata": topic.to_dict(), "message_count": counts[topic.name]}
                for topic in self.topics
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [info.path for info in self.files],
            "files": [info.to_dict() for info in self.files],
            "custom_data": dict(self.custom_data) if self.custom_data else None,
            "ros_distro": ROS_DISTRO,
        }

    def to_yaml(self) -> str:
        """The document without its wrapper, as MCAP's ``serialized_metadata`` and sqlite3 hold it."""
        return _dump(self.to_dict())

    def write(self, bag_directory: str | os.PathLike[str]) -> Path:
        """Write ``metadata.yaml`` atomically (temporary file, fsync, rename).

        A reader, or a crash, never sees a half-written file: either the previous complete version
        or the new one is there.
        """
        path = Path(bag_directory) / METADATA_FILENAME
        temporary = path.with_name(f".{METADATA_FILENAME}.tmp")
        text = _dump({"rosbag2_bagfile_information": self.to_dict()})
        try:
            with open(temporary, "w", encoding="utf-8") as file:
                file.write(text)
                file.flush()
                os.fsync(file.fileno())
            os.replace(temporary, path)
            fsync_directory(path.parent)  # the rename itself must survive a power loss
        except BaseException:
            temporary.unlink(missing_ok=True)
            raise
        return path


def fsync_directory(directory: Path) -> None:
    """Make the directory's entries (files created, renamed or removed in it) survive a power loss: an fsync of a
    file does not, by POSIX, make the file's name durable (docs/design/power-cut.md)."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
