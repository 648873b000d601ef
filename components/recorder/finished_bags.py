"""The final counts of the bags a recorder closed, for ``~/get_stats``: the last few of them, and how many in all.

A bag's final counts are taken when it closes, but two things can still change them afterwards, and the counts
must then say what the bag holds: a writer given up on at a stop (a slow disk) that writes what it held and
closes the bag after all (RecordingSession.finish), and messages received inside a recording window that a busy
executor hands to the intake only after the window's bag was closed (RecordingSession.missed). Such a bag is
marked :meth:`changed`; its counts are taken again the next time they are read.
"""
from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Any, Protocol


class ClosedBag(Protocol):
    """A closed bag whose counts can be read (RecordingSession)."""

    def stats(self) -> dict[str, Any]:
        """Its counts, as ``~/get_stats`` answers them."""


@dataclass
class _Entry:
    bag: ClosedBag | None  # only while its counts may still change: a bag holds its writer and its samples
    stats: dict[str, Any]
    changed: bool = False


class FinishedBags:
    """The final counts of the last ``kept`` bags closed (oldest first), and how many were closed in all."""

    def __init__(self, kept: int) -> None:
        self._entries: deque[_Entry] = deque(maxlen=kept)
        self._lock = threading.Lock()
        self.count = 0

    def add(self, bag: ClosedBag, may_change: bool) -> dict[str, Any]:
        """``bag`` was closed: keep its final counts (returned), and the bag itself if they ``may_change``."""
        stats = bag.stats()
        with self._lock:
            self._entries.append(_Entry(bag if may_change else None, stats))
            self.count += 1
        return stats

    def changed(self, bag: ClosedBag) -> None:
        """The counts of ``bag`` changed after it was closed (see module docstring)."""
        with self._lock:
            for entry in self._entries:
                if entry.bag is bag:
                    entry.changed = True

    def stats(self) -> list[dict[str, Any]]:
        """The final counts of the bags kept, oldest first; those that changed are taken again."""
        with self._lock:
            entries = list(self._entries)
        for entry in entries:
            if entry.changed and entry.bag is not None:
                entry.changed = False  # a change after this reading marks it again
                entry.stats = entry.bag.stats()
        return [entry.stats for entry in entries]
