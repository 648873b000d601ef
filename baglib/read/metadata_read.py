"""Reading ``metadata.yaml`` of every rosbag2 version a reader meets: 4 (Foxy) to 9 (Jazzy).

What changed between the versions (rosbag2_storage's ``yaml.hpp``, ``BagMetadata`` decode):
4 ``offered_qos_profiles`` as a YAML *string* with rmw's integer policies; 5 adds ``files`` (per-file
start, duration, count); 6 ``custom_data``; 7 ``type_description_hash``; 8 ``ros_distro``; 9 the QoS
profiles as a YAML list with string policies. Everything is returned in the version-9 form, so
the callers (the bag reader, ``bag info``) never look at a version number.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from baglib.format.metadata import METADATA_FILENAME, SAFE_LOADER, FileInfo, parse_qos_profiles
from baglib.format.bag_files import RECOVER_COMMAND, storage_files
from baglib.read.storage_reader import BagReadError

__all__ = ["SUPPORTED_VERSIONS", "StoredMetadata", "StoredTopic", "load_metadata", "metadata_from_text",
           "parse_metadata"]

SUPPORTED_VERSIONS = range(4, 10)


@dataclass(frozen=True)
class StoredTopic:
    """One ``topics_with_message_count`` entry, as written (rosbag2 allows names without the leading
    ``/``); ``offered_qos_profiles`` in :func:`.metadata.qos_profile_dict`'s form."""

    name: str
    type: str
    serialization_format: str
    offered_qos_profiles: tuple[dict[str, Any], ...]
    type_description_hash: str
    message_count: int


@dataclass(frozen=True)
class StoredMetadata:
    """A ``rosbag2_bagfile_information`` document, whatever its version, as written (no corrections:
    an empty bag keeps the ``starting_time`` its writer put there)."""

    version: int
    storage_identifier: str
    starting_time_ns: int
    duration_ns: int
    message_count: int
    topics: list[StoredTopic]
    relative_file_paths: list[str]
    #: Per-file entries, from version 5 on (empty before).
    files: list[FileInfo] = field(default_factory=list)
    compression_format: str = ""
    compression_mode: str = ""
    custom_data: dict[str, str] = field(default_factory=dict)
    ros_distro: str = ""


def load_metadata(bag_dir: str | Path) -> StoredMetadata:
    """Read ``bag_dir/metadata.yaml``.

    Raises:
        BagReadError: no such file (naming ``bag recover`` when storage files are there, as a crash
            leaves them), not YAML, a version outside :data:`SUPPORTED_VERSIONS`, a missing or
            malformed entry.
    """
    bag_dir = Path(bag_dir)
    path = bag_dir / METADATA_FILENAME
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as error:
        files = storage_files(bag_dir) if bag_dir.is_dir() else []
        if files:
            raise BagReadError(
                f"'{bag_dir}' is an unfinished bag: no {METADATA_FILENAME} next to "
                f"{', '.join(file.name for file in files)} (was the recording interrupted?). "
                f"Run `{RECOVER_COMMAND} {bag_dir}` to make it readable."
            ) from error
        if not bag_dir.exists():
            raise BagReadError(f"'{bag_dir}' does not exist") from error
        raise BagReadError(f"'{bag_dir}' is not a bag: no {METADATA_FILENAME}") from error
    except NotADirectoryError as error:
        raise BagReadError(f"'{bag_dir}' is a file, not a bag directory") from error
    except OSError as error:
        raise BagReadError(f"cannot read {path}: {error.strerror or error}") from error
    except UnicodeDecodeError as error:
        raise BagReadError(f"cannot read {path}: not UTF-8 text ({error.reason})") from error
    return metadata_from_text(text, str(path))


def metadata_from_text(text: str, source: str) -> StoredMetadata:
    """The metadata in ``text``, a ``metadata.yaml`` read from ``source`` (a path, or an object in a store)."""
    document = _load_yaml(text, source)
    if not isinstance(document, dict) or "rosbag2_bagfile_information" not in document:
        raise BagReadError(f"{source} has no rosbag2_bagfile_information")
    return parse_metadata(document["rosbag2_bagfile_information"], source)


def parse_metadata(document: Any, source: str) -> StoredMetadata:
    """The ``rosbag2_bagfile_information`` mapping, or the YAML text of it that a storage file keeps;
    ``source`` names where it came from in errors."""
    if isinstance(document, str):
        document = _load_yaml(document, source)
    if not isinstance(document, dict):
        raise BagReadError(f"{source}: the bag information is not a mapping")
    try:
        version = document["version"]
        if not isinstance(version, int) or version not in SUPPORTED_VERSIONS:
            raise BagReadError(
                f"{source}: metadata version {version!r} is not supported (this reader reads versions "
                f"{SUPPORTED_VERSIONS.start} to {SUPPORTED_VERSIONS.stop - 1})")
        optional = _optional_entries(document, version)
        return StoredMetadata(
            version=version,
            storage_identifier=str(document["storage_identifier"]),
            starting_time_ns=int(document["starting_time"]["nanoseconds_since_epoch"]),
            duration_ns=int(document["duration"]["nanoseconds"]),
            message_count=int(document["message_count"]),
            topics=[_topic(entry, source) for entry in document.get("topics_with_message_count") or []],
            relative_file_paths=[str(name) for name in document.get("relative_file_paths") or []],
            **optional,
        )
    except KeyError as error:
        raise BagReadError(f"{source}: no {error.args[0]!r} entry") from error
    except (TypeError, ValueError, AttributeError) as error:
        raise BagReadError(f"{source}: malformed entry ({error})") from error


def _load_yaml(text: str, source: str) -> Any:
    try:
        return yaml.load(text, Loader=SAFE_LOADER)  # noqa: S506 (a safe loader)
    except yaml.YAMLError as error:
        raise BagReadError(f"{source} is not YAML: {error}") from error


def _optional_entries(document: dict[str, Any], version: int) -> dict[str, Any]:
    """The entries later versions added (each read only from the version that has it)."""
    entries: dict[str, Any] = {
        "compression_format": str(document.get("compression_format") or ""),
        "compression_mode": str(document.get("compression_mode") or ""),
    }
    if version >= 5:
        entries["files"] = [
            FileInfo(str(entry["path"]), int(entry["starting_time"]["nanoseconds_since_epoch"]),
                     int(entry["duration"]["nanoseconds"]), int(entry["message_count"]))
            for entry in document.get("files") or []]
    if version >= 6:
        custom = document.get("custom_data") or {}
        entries["custom_data"] = {str(key): str(value) for key, value in custom.items()}
    if version >= 8:
        entries["ros_distro"] = str(document.get("ros_distro") or "")
    return entries


def _topic(entry: Any, source: str) -> StoredTopic:
    meta = entry["topic_metadata"]
    name = str(meta["name"])
    try:
        profiles = tuple(parse_qos_profiles(meta.get("offered_qos_profiles")))
    except ValueError as error:
        raise BagReadError(f"{source}: topic {name!r}: {error}") from error
    return StoredTopic(name, str(meta["type"]), str(meta["serialization_format"]), profiles,
                       str(meta.get("type_description_hash") or ""), int(entry["message_count"]))
