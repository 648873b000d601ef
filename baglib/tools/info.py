"""``ipc-component bag info``: what ``ros2 bag info`` prints, for users of the PyPI wheels (no ``ros2 bag``).

It reads ``metadata.yaml`` (versions 4 to 9, :mod:`.metadata_read`) and the sizes of the files it lists,
and formats them the way rosbag2_py's ``format_bag_meta_data`` (Jazzy) does: service event topics are listed
as services, not as topics, and their messages are not counted in ``Messages:``. A bag a crash left
unfinished (no ``metadata.yaml``, a file it does not list, an MCAP file without footer) is named as such,
with the command that repairs it.
"""
from __future__ import annotations

import datetime
from pathlib import Path

from baglib.format.mcap_records import MAGIC
from baglib.format.metadata import METADATA_FILENAME
from baglib.read.metadata_read import StoredMetadata, load_metadata
from baglib.format.bag_files import RECOVER_COMMAND, storage_files
from baglib.format.service_events import is_service_event_topic, service_name, service_type
from baglib.read.storage_reader import BagReadError

_LABEL_WIDTH = 19  # "Topic information: " and the padding of every other label
_SERVICE_LABEL_WIDTH = 21  # "Service information: ", which rosbag2 pads its service lines to


class BagInfoError(BagReadError):
    """The directory is not a readable rosbag2 bag."""


def _metadata(bag_dir: str | Path) -> StoredMetadata:
    try:
        return load_metadata(bag_dir)
    except BagReadError as error:
        raise BagInfoError(str(error)) from error


def _file_size(size: int) -> str:
    units = ("B", "KiB", "MiB", "GiB", "TiB")
    value, exponent = float(size), 0
    while value >= 1024 and exponent < len(units) - 1:
        value, exponent = value / 1024, exponent + 1
    return f"{size} B" if exponent == 0 else f"{value:.1f} {units[exponent]}"


def _time(nanoseconds: int) -> str:
    moment = datetime.datetime.fromtimestamp(nanoseconds / 1e9)
    seconds, fraction = divmod(nanoseconds, 1_000_000_000)
    # rosbag2's "%b %e %Y": the day padded with a space, not a zero
    return f"{moment:%b} {moment.day:2d} {moment:%Y %H:%M:%S}.{fraction:09d} ({seconds}.{fraction:09d})"


def _block(label: str, lines: list[str], width: int = _LABEL_WIDTH) -> list[str]:
    pad = " " * width
    first = f"{label:<{width}}"
    return [first + (lines[0] if lines else "")] + [pad + line for line in lines[1:]]


def _unfinished(bag_dir: Path, listed: list[str]) -> list[str]:
    """Warnings about storage files a crash left behind: unlisted ones, MCAP files without footer."""
    notes = []
    for path in storage_files(bag_dir) if bag_dir.is_dir() else []:
        if path.name not in listed:
            notes.append(f"{path.name} is not listed in {METADATA_FILENAME} (recording interrupted?)")
        elif path.suffix == ".mcap":
            with open(path, "rb") as file:
                file.seek(max(0, path.stat().st_size - len(MAGIC)))
                if file.read() != MAGIC:
                    notes.append(f"{path.name} is unfinished: no MCAP footer")
    if notes:
        notes.append(f"Run `{RECOVER_COMMAND} {bag_dir}` to make the whole bag readable.")
    return [f"Warning: {note}" for note in notes]


def format_bag_info(bag_dir: str | Path) -> str:
    """The ``ros2 bag info`` text for ``bag_dir`` (``metadata.yaml`` of any version from 4 to 9)."""
    meta = _metadata(bag_dir)
    files = [info.path for info in meta.files] or meta.relative_file_paths
    size = sum((Path(bag_dir) / f).stat().st_size for f in files if (Path(bag_dir) / f).exists())
    start, duration = meta.starting_time_ns, meta.duration_ns
    topics: list[str] = []
    services: list[str] = []
    service_messages = 0
    for topic in meta.topics:
        if is_service_event_topic(topic.name, topic.type):
            service_messages += topic.message_count
            services.append(f"Service: {service_name(topic.name)} | Type: {service_type(topic.type)} | "
                            f"Event Count: {topic.message_count} | "
                            f"Serialization Format: {topic.serialization_format}")
        else:
            topics.append(f"Topic: {topic.name} | Type: {topic.type} | Count: {topic.message_count} | "
                          f"Serialization Format: {topic.serialization_format}")
    lines = [
        *_block("Files:", files),
        *_block("Bag size:", [_file_size(size)]),
        *_block("Storage id:", [meta.storage_identifier]),
        *_block("ROS Distro:", [meta.ros_distro or "unknown"]),
        *_block("Duration:", [f"{duration // 1_000_000_000}.{duration % 1_000_000_000:09d}s"]),
        *_block("Start:", [_time(start)]),
        *_block("End:", [_time(start + duration)]),
        *_block("Messages:", [str(meta.message_count - service_messages)]),
        *_block("Topic information:", topics),
        *_block("Service:", [str(len(services))]),
        *_block("Service information:", services, _SERVICE_LABEL_WIDTH),
        *_unfinished(Path(bag_dir), files),
    ]
    return "\n".join(line.rstrip() for line in lines)
