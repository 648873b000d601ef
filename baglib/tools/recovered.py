"""What recovering one storage file found: its report line, its entry and topics for ``metadata.yaml``, and how
to repair it (in place or by a copy). Shared by the MCAP and SQLite3 repairs and the ``bag recover`` driver."""
from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from baglib.format.metadata import METADATA_FILENAME, SAFE_LOADER, FileInfo, TopicInfo
from baglib.tools.patch_journal import Patch

__all__ = ["FileReport", "Recovered", "custom_data_of", "load_yaml", "topic_of"]


@dataclass
class FileReport:
    """What recovering one storage file did: ``action`` is ``intact``, ``repaired`` or ``left out``."""

    name: str
    action: str = "intact"
    messages: int = 0
    bytes_cut: int = 0
    reasons: list[str] = field(default_factory=list)

    def line(self) -> str:
        if self.action == "left out":
            return f"{self.name}: left out ({'; '.join(self.reasons)})"
        text = f"{self.name}: {self.action}, {self.messages} messages kept"
        if self.bytes_cut:
            text += f", {self.bytes_cut} bytes cut"
        return text + "".join(f"; {reason}" for reason in self.reasons)


@dataclass
class Recovered:
    """One file's recoverable content: its entry, topics and a writer of the repaired file."""

    report: FileReport
    info: FileInfo
    topics: list[TopicInfo]
    custom_data: dict[str, str] | None
    #: Writes the repaired file at the temporary path, given the bag's metadata to close it with;
    #: ``None`` when the file is intact (or was repaired in place already) and is kept as it is.
    write: Callable[[Path, str], None] | None
    #: The in-place repair, given the bag's metadata: a :class:`Patch` of the file, or ``None`` when only
    #: a copy can repair it (then ``write`` does).
    patch: Callable[[str], Patch | None] | None = None


def topic_of(report: FileReport, name: str, type_name: str, serialization_format: str, qos: Any,
           type_hash: str) -> TopicInfo | None:
    """The topic as the file describes it, or ``None`` (and a note) if the description is unusable."""
    with contextlib.suppress(yaml.YAMLError, TypeError):
        qos = load_yaml(qos) if isinstance(qos, str) else qos
    profiles = qos if isinstance(qos, list) and all(isinstance(p, dict) for p in qos) else []
    try:
        return TopicInfo(name, type_name, serialization_format, profiles, type_hash)
    except (ValueError, TypeError, AttributeError) as error:
        report.reasons.append(f"topic {name!r} not listed in {METADATA_FILENAME}: {error}")
        return None


def custom_data_of(document: Any) -> dict[str, str] | None:
    custom = document.get("custom_data") if isinstance(document, dict) else None
    if isinstance(custom, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in custom.items()):
        return custom or None
    return None


def load_yaml(text: str) -> Any:
    return yaml.load(text, Loader=SAFE_LOADER)  # noqa: S506 (a safe loader)
