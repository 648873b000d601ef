"""The files of a bag directory: which ones hold messages, in which order, what shows a crash left them
unfinished, and the command that repairs them.

Shared by the read path (to name the repair in its errors) and by the tools (``info``, ``recover``, ``merge``), so
that neither the readers nor ``info`` need to import the repair tool.
"""
from __future__ import annotations

import re
from collections.abc import Collection
from pathlib import Path

from baglib.format.mcap_records import MAGIC

__all__ = ["RECOVER_COMMAND", "STORAGE_EXTENSIONS", "storage_files", "unfinished_files"]

RECOVER_COMMAND = "ipc-component bag recover"
STORAGE_EXTENSIONS = {".mcap": "mcap", ".db3": "sqlite3"}


def storage_files(bag: Path) -> list[Path]:
    """The directory's storage files in recording order (``<name>_<N>`` by N, then by name)."""
    def order(path: Path) -> tuple[int, str]:
        number = re.search(r"_(\d+)$", path.stem)
        return (int(number.group(1)) if number else 2**63, path.name)

    return sorted((path for path in bag.iterdir()
                   if path.suffix in STORAGE_EXTENSIONS and not path.name.startswith(".") and path.is_file()),
                  key=order)


def unfinished_files(bag: Path, listed: Collection[str] | None = None) -> list[str]:
    """What shows that a crash left ``bag`` unfinished, one note per file: in a bag directory, a storage file
    ``listed`` (the names ``metadata.yaml`` lists) does not name; for any storage file (``bag`` itself when it is
    one), an MCAP file without its closing magic, or an SQLite3 database next to a rollback journal or a
    write-ahead log that holds frames (a clean close removes both). ``[]``: nothing unfinished."""
    files = storage_files(bag) if bag.is_dir() else [bag]
    notes = []
    for path in files:
        if listed is not None and path.name not in listed:
            notes.append(f"{path.name} is not listed in metadata.yaml (recording interrupted?)")
        elif path.suffix == ".mcap" and not _closed_mcap(path):
            notes.append(f"{path.name} is unfinished: no MCAP footer")
        elif path.suffix == ".db3":
            journal, log = (path.with_name(path.name + suffix) for suffix in ("-journal", "-wal"))
            if journal.exists() or (log.exists() and log.stat().st_size > 0):
                notes.append(f"{path.name} is unfinished: a crash left its "
                             f"{'rollback journal' if journal.exists() else 'write-ahead log'}")
    return notes


def _closed_mcap(path: Path) -> bool:
    with open(path, "rb") as file:
        file.seek(max(0, path.stat().st_size - len(MAGIC)))
        return file.read() == MAGIC
