"""``ipc-component bag info``: what ``ros2 bag info`` prints, for users of the PyPI wheels (no ``ros2 bag``).

It reads ``metadata.yaml`` (version 9) and the sizes of the files it lists, and formats them the way
rosbag2_cpp's ``format_bag_meta_data`` does.
"""
from __future__ import annotations

import datetime
from pathlib import Path
from typing import Any

import yaml

from baglib.metadata import METADATA_FILENAME

_LABEL_WIDTH = 19  # "Topic information: " and the padding of every other label


class BagInfoError(Exception):
    """The directory is not a readable rosbag2 bag."""


def read_metadata(bag_dir: str | Path) -> dict[str, Any]:
    path = Path(bag_dir) / METADATA_FILENAME
    try:
        document = yaml.safe_load(path.read_text())
        return document["rosbag2_bagfile_information"]
    except FileNotFoundError as exc:
        raise BagInfoError(f"'{bag_dir}' is not a bag: no {METADATA_FILENAME}") from exc
    except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
        raise BagInfoError(f"cannot read {path}: {exc}") from exc


def _file_size(size: int) -> str:
    units = ("B", "KiB", "MiB", "GiB", "TiB")
    value, exponent = float(size), 0
    while value >= 1024 and exponent < len(units) - 1:
        value, exponent = value / 1024, exponent + 1
    return f"{size} B" if exponent == 0 else f"{value:.1f} {units[exponent]}"


def _time(nanoseconds: int) -> str:
    moment = datetime.datetime.fromtimestamp(nanoseconds / 1e9)
    seconds, fraction = divmod(nanoseconds, 1_000_000_000)
    return f"{moment:%b %d %Y %H:%M:%S}.{fraction:09d} ({seconds}.{fraction:09d})"


def _block(label: str, lines: list[str]) -> list[str]:
    pad = " " * _LABEL_WIDTH
    first = f"{label:<{_LABEL_WIDTH}}"
    return [first + (lines[0] if lines else "")] + [pad + line for line in lines[1:]]


def format_bag_info(bag_dir: str | Path) -> str:
    """The ``ros2 bag info`` text for ``bag_dir``."""
    meta = read_metadata(bag_dir)
    files = [f["path"] for f in meta.get("files") or []] or list(meta.get("relative_file_paths") or [])
    size = sum((Path(bag_dir) / f).stat().st_size for f in files if (Path(bag_dir) / f).exists())
    start = int(meta["starting_time"]["nanoseconds_since_epoch"])
    duration = int(meta["duration"]["nanoseconds"])
    topics = [
        f"Topic: {t['topic_metadata']['name']} | Type: {t['topic_metadata']['type']} | "
        f"Count: {t['message_count']} | Serialization Format: {t['topic_metadata']['serialization_format']}"
        for t in meta.get("topics_with_message_count") or []]
    lines = [
        *_block("Files:", files),
        *_block("Bag size:", [_file_size(size)]),
        *_block("Storage id:", [meta.get("storage_identifier", "")]),
        *_block("ROS Distro:", [meta.get("ros_distro", "")]),
        *_block("Duration:", [f"{duration // 1_000_000_000}.{duration % 1_000_000_000:09d}s"]),
        *_block("Start:", [_time(start)]),
        *_block("End:", [_time(start + duration)]),
        *_block("Messages:", [str(meta.get("message_count", 0))]),
        *_block("Topic information:", topics),
        *_block("Services:", ["0"]),
        *_block("Service information:", []),
    ]
    return "\n".join(line.rstrip() for line in lines)
