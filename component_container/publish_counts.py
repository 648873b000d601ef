"""What each component has published, counted on the publish path, and how ``/diagnostics`` carries it.

Every publisher a :class:`~component_container.component_node.ComponentNode` creates counts its messages and
their rough serialized bytes, and remembers when it last published (steady clock). The container reports the
counts per topic in each component's status, once a second; a viewer (``ipc-component top``) gets rates and
bandwidth from two reports. Dividing by the time between the *last publishes* of the two reports, rather than
between the reports, counts whole message periods: a 10 Hz topic reads 10 Hz, not 9 or 11 depending on where the
report fell between two messages.

The publish path pays one tuple assignment and one clock read per message, no lock: the publishing thread
replaces :attr:`PublishCounter.state` in a single store, so the diagnostics thread always reads a consistent
(messages, bytes, last) triple. Two threads publishing on one publisher at the same moment may lose one count.
"""
from __future__ import annotations

import re
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

#: Key prefix of one published topic in a component's status: ``published /front_camera/image_raw``.
PUBLISHED_PREFIX = "published "
#: Key of the container's uptime in its own status (seconds on its steady clock, to the microsecond): the
#: instant the report was taken, which the ages of the last publishes are relative to.
UPTIME = "uptime (s)"

_VALUE = re.compile(r"(\d+) messages, (\d+) bytes(?:, last ([0-9.]+) s ago)?")


def data_size(message: Any) -> int:
    """Bytes of a message's ``data`` buffer (Image, PointCloud2, CompressedImage, ...); 0 without one."""
    data = getattr(message, "data", None)
    if not hasattr(data, "__len__"):
        return 0
    return len(data) * getattr(data, "itemsize", 1)


class PublishCounter:
    """Messages one publisher has published, their rough bytes, and when the last one went out.

    The bytes of a message are its ``data`` buffer plus the rest of the first message this publisher sent,
    measured once by serializing it: exact for the sensor messages, whose other fields keep their size.
    """

    __slots__ = ("_overhead", "state")

    def __init__(self) -> None:
        #: (messages, bytes, monotonic ns of the last publish; 0 before the first)
        self.state: tuple[int, int, int] = (0, 0, 0)
        self._overhead: int | None = None

    def count(self, message: Any) -> None:
        """One message published: an object, or its serialization (``bytes``)."""
        if isinstance(message, bytes):
            self.count_bytes(len(message))
            return
        if self._overhead is None:
            self._overhead = _overhead(message)
        self.count_bytes(self._overhead + data_size(message))

    def count_bytes(self, size: int) -> None:
        """One message of ``size`` bytes published (a serialized one)."""
        messages, total, _ = self.state
        self.state = (messages + 1, total + size, time.monotonic_ns())


def _overhead(message: Any) -> int:
    """Serialized bytes of ``message`` outside its ``data`` buffer (0 if it cannot be serialized)."""
    # Imported here, once per publisher: the CLI reads this module's reports without loading rclpy.
    from rclpy.serialization import serialize_message

    try:
        return max(0, len(serialize_message(message)) - data_size(message))
    except Exception:  # noqa: BLE001 - an estimate only: a message rclpy refuses goes out (or fails) elsewhere
        return 0


@dataclass(frozen=True)
class Published:
    """One topic's counts as a report carries them; ``age`` in seconds before the report, None if never."""

    messages: int
    bytes: int
    age: float | None


def publication_values(counters: Iterable[tuple[str, PublishCounter]], now_ns: int) -> dict[str, str]:
    """Status values for a component's publishers (summed per topic), ages taken at ``now_ns``."""
    topics: dict[str, tuple[int, int, int]] = {}
    for topic, counter in counters:
        messages, size, last = counter.state
        seen = topics.get(topic, (0, 0, 0))
        topics[topic] = (seen[0] + messages, seen[1] + size, max(seen[2], last))
    values = {}
    for topic in sorted(topics):
        messages, size, last = topics[topic]
        text = f"{messages} messages, {size} bytes"
        if messages:
            text += f", last {max(0, now_ns - last) / 1e9:.6f} s ago"
        values[PUBLISHED_PREFIX + topic] = text
    return values


def parse_publication(key: str, value: str) -> tuple[str, Published] | None:
    """``(topic, counts)`` of one status value written by :func:`publication_values`; None for other keys."""
    if not key.startswith(PUBLISHED_PREFIX):
        return None
    match = _VALUE.fullmatch(value)
    if match is None:
        return None
    age = match.group(3)
    return key[len(PUBLISHED_PREFIX):], Published(int(match.group(1)), int(match.group(2)),
                                                  None if age is None else float(age))
