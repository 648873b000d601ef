"""The recorder's health for ``/diagnostics``: its level, and the numbers an operator watches while recording.

Rates and "dropped recently" are measured between two samples (the container takes one about once a second).
"""
from __future__ import annotations

import threading
import time
from typing import Any

from component_container.health import DROPPED, ERROR, FREE_DISK_MB, OK, WARN, Health


class HealthMonitor:
    """Turns a session's live stats into a :class:`Health`; thread-safe, never touches the storage."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        # the previous sample: bag, monotonic time, bytes written, messages dropped
        self._previous: tuple[str, float, int, int] | None = None

    def sample(self, stats: dict[str, Any] | None, paused: bool) -> Health:
        """``stats``: RecordingSession.stats() of the current bag, None when not recording."""
        if stats is None:
            return Health(WARN, "not recording")
        topics = stats["topics"].values()
        dropped = sum(t["dropped"] for t in topics)
        now = time.monotonic()
        with self._lock:
            previous, self._previous = self._previous, (stats["bag"], now, stats["bytes_written"], dropped)
        if previous is not None and previous[0] == stats["bag"] and now > previous[1]:
            interval = now - previous[1]
            rate = (stats["bytes_written"] - previous[2]) / interval / 1e6
            recent_drops = dropped - previous[3]
        else:
            interval, rate, recent_drops = 0.0, 0.0, dropped
        values = {
            "bag": stats["bag"],
            "current file": stats["current_file"],
            "write rate (MB/s)": f"{rate:.2f}",
            "received": str(sum(t["received"] for t in topics)),
            "written": str(sum(t["written"] for t in topics)),
            DROPPED: str(dropped),
            "rate limited": str(sum(t["rate_limited"] for t in topics)),
            FREE_DISK_MB: f"{stats['free_bytes'] / 1e6:.0f}",
            "time to min_free_space (s)": ("not writing" if stats["seconds_until_min_free"] is None
                                           else f"{stats['seconds_until_min_free']:.0f}"),
            "backlog (MB)": f"{stats['backlog_bytes'] / 1e6:.1f}",
            "behind (s)": f"{stats['backlog_s']:.2f}",
        }
        if stats["error"]:
            return Health(ERROR, f"recording stopped: {stats['error']}", values)
        if paused:
            return Health(WARN, "paused", values)
        if recent_drops:
            since = f"in the last {interval:.1f} s" if interval else "so far"
            return Health(WARN, f"{recent_drops} messages dropped {since}", values)
        if stats["reserve_in_use_bytes"]:
            return Health(WARN, f"writer behind: {stats['backlog_bytes'] / 1e6:.0f} MB not yet written "
                                f"({stats['backlog_s']:.1f} s), in the stall reserve", values)
        return Health(OK, "recording", values)

