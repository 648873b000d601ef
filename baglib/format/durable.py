"""Making what was written survive a power cut: fsync of a file, and of a directory (its entries: a created,
renamed or removed name is durable only once its directory is synced)."""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["fsync_directory", "fsync_file"]


def fsync_file(path: Path) -> None:
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def fsync_directory(directory: Path) -> None:
    """Make the directory's entries (files created, renamed or removed in it) survive a power loss: an fsync of a
    file does not, by POSIX, make the file's name durable (docs/design/power-cut.md)."""
    descriptor = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)
