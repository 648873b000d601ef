"""``record.max_rates``: per-topic rate limits, messages left out of a bag by design.

Why: a long test day cannot keep every LiDAR scan and camera frame; a LiDAR at 2 Hz and cameras at 5 Hz may be
enough. rosbag2 has no such parameter; this one is the recorder's own.

Form: a list of ``"PATTERN:RATE"`` strings (a ROS parameter cannot be a map), e.g.
``['/lidar/points:2', '/cam.*/image_raw:5']``. ``PATTERN`` is a regular expression matched against the whole
topic name (a plain topic name matches itself); ``RATE`` is the most messages per second to keep. The first
entry whose pattern matches a topic applies to it; a topic no entry matches is not limited. The last ``:``
separates the rate, so a pattern may contain colons.

Which messages are kept: the first one, then the first one received at or after each due time, which advances
by one period per kept message (``1 / RATE``, on the receive time, the bag's log time). So a 30 Hz camera
limited to 5 Hz keeps every sixth frame on average whatever its jitter; after a pause longer than a period the
due time restarts from the next message, so a pause is never made up by a burst.

A message left out is *rate limited*: counted per topic (``rate_limited`` in ``~/get_stats`` and the final
counts), never as a loss (``dropped``, ``drop_reasons`` and ``events/messages_lost`` are losses only).
"""
from __future__ import annotations

import re
import threading
from collections import Counter

from components.bounds import Bounds

#: Rates a limit may set, in messages per second.
MAX_RATE = Bounds(0.001, 1_000_000, "Hz")
#: The reason a message is left out, as the stats name it.
RATE_LIMITED = "rate_limited"


def parse_max_rates(entries: list[str], label: str = "'record.max_rates'") -> list[tuple[re.Pattern[str], float]]:
    """``"PATTERN:RATE"`` strings as (compiled pattern, rate); ValueError naming ``label`` and the entry."""
    limits = []
    for entry in entries:
        pattern, separator, rate_text = entry.rpartition(":")
        if not separator or not pattern:
            raise ValueError(f"parameter {label} entries must be 'TOPIC_OR_REGEX:RATE', got {entry!r}")
        try:
            rate = float(rate_text)
        except ValueError:
            raise ValueError(f"parameter {label}: the rate of {entry!r} is not a number") from None
        MAX_RATE.check(f"{label} ({entry!r})", rate)
        try:
            limits.append((re.compile(pattern), rate))
        except re.error as exc:
            raise ValueError(f"parameter {label}: {pattern!r} of {entry!r} is not a valid regular expression: "
                             f"{exc}") from None
    return limits


class RateLimiter:
    """Decides per message whether a rate-limited topic keeps it, and counts what it leaves out.

    Thread-safe: intra-process messages arrive on their publishers' threads.
    """

    def __init__(self, limits: list[tuple[re.Pattern[str], float]]) -> None:
        self._limits = limits
        self._periods: dict[str, int | None] = {}  # per topic: nanoseconds between kept messages, None: no limit
        self._due_ns: dict[str, int] = {}
        self._lock = threading.Lock()
        self._left_out: Counter[str] = Counter()

    def admits(self, topic: str, log_time_ns: int) -> bool:
        """True: record the message; False: it is left out and counted as rate limited."""
        period = self._periods.get(topic, 0)
        if period == 0:
            period = self._periods[topic] = self._period_of(topic)
        if period is None:
            return True
        with self._lock:
            due = self._due_ns.get(topic)
            if due is not None and log_time_ns < due:
                self._left_out[topic] += 1
                return False
            # The next due time is one period on; after a pause (or the first message) one period from now.
            self._due_ns[topic] = due + period if due is not None and log_time_ns < due + period \
                else log_time_ns + period
            return True

    def limits(self, topic: str) -> bool:
        """Whether an entry applies to ``topic``."""
        return self._period_of(topic) is not None

    def left_out(self) -> Counter[str]:
        """Per topic: messages left out so far (a copy)."""
        with self._lock:
            return Counter(self._left_out)

    def _period_of(self, topic: str) -> int | None:
        for pattern, rate in self._limits:
            if pattern.fullmatch(topic):
                return round(1e9 / rate)
        return None
