"""The player's read-ahead: messages read on a thread of their own, ahead of the playback thread, in a
queue bounded by count and bytes.

rosbag2's player keeps ``read_ahead_queue_size`` messages queued by a loader thread; this does the same and
also bounds the queue's bytes (a count alone lets 1000 camera frames take 6 GB). A run is one pass over the
bag from a start time: ``restart`` (play, seek, loop) drops what is queued and starts a new pass; the
playback thread sees the new pass's messages only. Reading mostly waits on the file (the GIL released);
turning messages into objects is left to the playback thread (see playback.py), which knows when it has time.
"""
from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Collection
from itertools import islice
from typing import Any

from baglib.read.reader import BagMessage
from baglib.read.timeline import Timeline


class Queued:
    """A queued message and what the playback thread prepared for it (``None``: not yet, or nothing)."""

    __slots__ = ("message", "prepared", "ready")

    def __init__(self, message: BagMessage) -> None:
        self.message = message
        self.prepared: Any = None
        self.ready = False


class ReadAhead:
    """A loader thread over the bags' timeline; the playback thread ``peek``s and ``pop``s."""

    def __init__(self, reader: Timeline, topics: Collection[str], max_messages: int, max_bytes: int,
                 on_error: Callable[[BaseException], None]) -> None:
        self._reader = reader
        self._topics = list(topics)
        self._max_messages = max_messages
        self._max_bytes = max_bytes
        self._on_error = on_error
        self._queue: deque[Queued] = deque()
        self._bytes = 0
        self._pass = 0            # bumped by restart(): the loader drops a pass that is no longer wanted
        self._pass_done = True    # the current pass reached its end (or failed)
        self._start_ns = 0
        self._stop_ns: int | None = None
        self._closed = False
        self._changed = threading.Condition()
        self.starved = 0          # times the playback thread found the queue empty before the pass ended
        self._thread = threading.Thread(target=self._load, name="player-read-ahead", daemon=True)
        self._thread.start()

    def restart(self, start_ns: int, stop_ns: int | None = None) -> None:
        """Drop the queue and read again from ``start_ns`` (inclusive) to ``stop_ns`` (exclusive)."""
        with self._changed:
            self._queue.clear()
            self._bytes = 0
            self._pass += 1
            self._pass_done = False
            self._start_ns, self._stop_ns = start_ns, stop_ns
            self._changed.notify_all()

    def peek(self, timeout: float) -> Queued | None:
        """The next message of the current pass, waiting up to ``timeout`` s for the loader; None at the end
        of the pass, or when the wait timed out (``at_end`` tells which)."""
        with self._changed:
            if not self._queue and not self._pass_done:
                self.starved += 1
                self._changed.wait_for(lambda: self._queue or self._pass_done or self._closed, timeout)
            return self._queue[0] if self._queue else None

    def head(self, count: int) -> list[Queued]:
        """The first ``count`` queued messages (a snapshot: the loader may append meanwhile)."""
        with self._changed:
            return list(islice(self._queue, count))

    def pop(self) -> None:
        with self._changed:
            if self._queue:
                self._bytes -= _size(self._queue.popleft().message)
                self._changed.notify_all()

    @property
    def at_end(self) -> bool:
        """The current pass is fully read and fully taken."""
        with self._changed:
            return self._pass_done and not self._queue

    def close(self) -> None:
        with self._changed:
            self._closed = True
            self._pass += 1
            self._changed.notify_all()
        self._thread.join(5.0)

    # --- the loader thread --------------------------------------------------------------------------------
    def _load(self) -> None:
        while True:
            with self._changed:
                self._changed.wait_for(lambda: self._closed or not self._pass_done)
                if self._closed:
                    return
                current, start, stop = self._pass, self._start_ns, self._stop_ns
            try:
                self._read_pass(current, start, stop)
            except Exception as exc:  # noqa: BLE001 - a damaged file ends the pass; the player reports it
                self._on_error(exc)
            with self._changed:
                if self._pass == current:
                    self._pass_done = True
                    self._changed.notify_all()

    def _read_pass(self, current: int, start_ns: int, stop_ns: int | None) -> None:
        messages = self._reader.messages(self._topics, start_ns, stop_ns)
        try:
            for message in messages:
                size = _size(message)
                with self._changed:
                    self._changed.wait_for(lambda: self._pass != current or not self._full(size))
                    if self._pass != current:
                        return
                    self._queue.append(Queued(message))
                    self._bytes += size
                    self._changed.notify_all()
        finally:
            messages.close()  # type: ignore[attr-defined]  # a generator: releases its files' positions

    def _full(self, size: int) -> bool:
        if not self._queue:
            return False  # one message always fits, however big
        return len(self._queue) >= self._max_messages or self._bytes + size > self._max_bytes


def _size(message: BagMessage) -> int:
    return len(message.data) if isinstance(message.data, bytes) else message.data.nbytes
