"""When a recording begins and ends: scheduled instants on this computer's clock, for fleet recording.

``ipc-component record start`` loads a recorder into every container of a robot and gives each the same
instant (corrected by that container's clock offset) in ``record.start_at``; ``record stop`` later sets
``record.stop_at``. Each recorder subscribes at load, and writes exactly the messages *received* at or after
the start and before the stop (receive time: the instant of ``publish()`` in-process, the middleware's receive
timestamp over DDS), so every computer cuts at the same instant whatever the latency of the commands.

``record.max_duration`` ends the recording that long after its start even if no stop ever arrives (a network
partition must not leave a robot recording until its disk is full). ``record.split_at`` schedules a split.
Instants are seconds since the epoch (float), 0 meaning "none" (for the start: at load).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

#: Instants accepted: 0 (none), or between these (2001 and 2286: a date, not a duration given by mistake).
EARLIEST, LATEST = 1e9, 1e10
#: At most a year of recording per ``record.max_duration``.
MAX_DURATION = 365 * 86400.0
#: How long after the stop instant the bag is finalized: messages received just before the stop may still be on
#: their way through the executor (DDS) when the instant passes.
FINALIZE_GRACE_NS = 300_000_000


def instant_ns(name: str, seconds: float) -> int:
    """``seconds`` since the epoch as integer ns, 0 for none; ValueError naming ``name`` otherwise."""
    if seconds == 0:
        return 0
    if not EARLIEST <= seconds <= LATEST:
        raise ValueError(f"parameter '{name}' must be seconds since the epoch (between {EARLIEST:.0f} and "
                         f"{LATEST:.0f}) or 0 for none, got {seconds!r}")
    return round(seconds * 1e9)


def duration_ns(name: str, seconds: float) -> int:
    if not 0 <= seconds <= MAX_DURATION:
        raise ValueError(f"parameter '{name}' must be 0 (no limit) to {MAX_DURATION:.0f} s, got {seconds!r}")
    return round(seconds * 1e9)


@dataclass
class Schedule:
    """The recording window and a pending split; thread-safe (the intake reads it from publishers' threads)."""

    start_ns: int = 0
    stop_ns: int = 0
    max_duration_ns: int = 0
    split_ns: int = 0

    def __post_init__(self) -> None:
        self._lock = threading.Lock()
        self._end_ns = self._compute_end()

    def _compute_end(self) -> int:
        ends = [end for end in (self.stop_ns, self.start_ns + self.max_duration_ns if self.max_duration_ns else 0)
                if end]
        return min(ends) if ends else 0

    @property
    def end_ns(self) -> int:
        """The first instant not recorded any more (0: none)."""
        return self._end_ns

    def admits(self, received_ns: int) -> bool:
        """Whether a message received at ``received_ns`` belongs to the recording."""
        end = self._end_ns
        return received_ns >= self.start_ns and (not end or received_ns < end)

    def set_stop(self, stop_ns: int) -> None:
        with self._lock:
            self.stop_ns = stop_ns
            self._end_ns = self._compute_end()

    def set_split(self, split_ns: int) -> None:
        with self._lock:
            self.split_ns = split_ns

    def split_due(self, now_ns: int) -> bool:
        """True once when the scheduled split instant has come."""
        with self._lock:
            if self.split_ns and now_ns >= self.split_ns:
                self.split_ns = 0
                return True
            return False

    def finalize_due(self, now_ns: int) -> bool:
        """Whether the window has ended and the messages received within it had time to arrive."""
        end = self._end_ns
        return bool(end) and now_ns >= end + FINALIZE_GRACE_NS
