"""The files of a bag directory: which ones hold messages, in which order, and the command that repairs them.

Shared by the read path (to name the repair in its errors) and by the tools (``info``, ``recover``), so that
neither the readers nor ``info`` need to import the repair tool.
"""
from __future__ import annotations

import re
from pathlib import Path

__all__ = ["RECOVER_COMMAND", "STORAGE_EXTENSIONS", "storage_files"]

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
