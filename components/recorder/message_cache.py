"""The hand-off between the recorder's intake callbacks and its writer thread.

The intake side (the executor, or a publisher's thread for intra-process messages) must never wait on the
disk: it only appends to this cache. The cache is bounded by ``max_cache_size`` bytes, counting both queued
messages and those the writer holds until it has written them (so the bound is the recorder's whole buffer,
not one half of a double buffer); a message that does not fit is dropped and counted for its topic (never
silently lost). In snapshot mode the cache is a ring instead: the oldest messages make room, and nothing is
written until a snapshot is requested.
"""
from __future__ import annotations

import threading
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any


@dataclass(slots=True)
class CachedMessage:
    """One received message: a message object (intra-process) or CDR bytes (DDS), with its stamps."""

    topic: str
    payload: Any
    size: int
    log_time_ns: int
    publish_time_ns: int


def payload_size(payload: Any) -> int:
    """Bytes a payload will occupy: exact for CDR bytes, the data buffer plus headers for messages."""
    if isinstance(payload, (bytes, bytearray, memoryview)):
        return len(payload)
    data = getattr(payload, "data", None)
    return 256 + (len(data) if hasattr(data, "__len__") else 0)


class MessageCache:
    """A byte-bounded FIFO with per-topic drop counts; ``take_all`` blocks until data or close."""

    def __init__(self, max_bytes: int, ring: bool = False) -> None:
        self.max_bytes = max_bytes
        self._ring = ring
        self._queue: deque[CachedMessage] = deque()
        self._bytes = 0
        self._closed = False
        self.received: Counter[str] = Counter()  # every push, counted under the lock (pushers may race)
        self.dropped: Counter[str] = Counter()
        self.evicted: Counter[str] = Counter()
        self._condition = threading.Condition()

    @property
    def bytes(self) -> int:
        return self._bytes

    def push(self, message: CachedMessage) -> bool:
        """Queue a message; False (and counted) if it was dropped because the cache is full or closed."""
        with self._condition:
            self.received[message.topic] += 1
            if self._closed:
                self.dropped[message.topic] += 1
                return False
            if self._ring:
                while self._queue and self._bytes + message.size > self.max_bytes:
                    old = self._queue.popleft()
                    self._bytes -= old.size
                    self.evicted[old.topic] += 1
            elif self._queue and self._bytes + message.size > self.max_bytes:
                self.dropped[message.topic] += 1
                return False
            self._queue.append(message)
            self._bytes += message.size
            if not self._ring:
                self._condition.notify()
            return True

    def take_all(self, timeout: float | None = None) -> list[CachedMessage]:
        """Everything queued, waiting up to ``timeout`` for something to arrive (ring caches never wake)."""
        with self._condition:
            if not self._queue and not self._closed:
                self._condition.wait(timeout)
            return self._drain()

    def drain(self) -> list[CachedMessage]:
        """Everything queued, without waiting (a snapshot, or the final flush)."""
        with self._condition:
            return self._drain()

    def _drain(self) -> list[CachedMessage]:
        batch = list(self._queue)
        self._queue.clear()
        if self._ring:  # a snapshot hands its bytes over at once
            self._bytes = 0
        return batch

    def release(self, message: CachedMessage) -> None:
        """The writer is done with ``message``: its bytes stop counting against the bound."""
        with self._condition:
            if not self._ring:  # a ring's bytes were handed over with the snapshot
                self._bytes -= message.size

    def close(self) -> None:
        """Refuse new messages (they count as dropped) and wake the writer for its final flush."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed
