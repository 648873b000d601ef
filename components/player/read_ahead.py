"""The player's read-ahead: messages read on a thread of their own, ahead of the playback thread, in a
queue bounded by count and bytes.

rosbag2's player keeps ``read_ahead_queue_size`` messages queued by a loader thread; this does the same and
also bounds the queue's bytes (a count alone lets 1000 camera frames take 6 GB). A run is one pass over the
bag from a start time: ``restart`` (play, seek, loop) drops what is queued and starts a new pass; the
playback thread sees the new pass's messages only. Reading mostly waits on the file (the GIL released);
turning messages into objects is left to the playback thread (see playback.py), which knows when it has time.
Compressed images to decode (a :class:`Decoder`, components/player/decoded_topics.py) are handed, as they are
read, to their stream's own decoding thread (decode_worker.py): a stream's decoder needs its messages in
recorded order, each pass from its start, which is this thread's order. The byte bound counts the decoded
pictures, each at the size its stream's previous one had. When a run ends (:meth:`ReadAhead.halt`) the pass ends
too, and with it the decoding threads.

Publish-time order (``play.message_order`` SENT_TIMESTAMP, rosbag2 #1876): the bag is read in receive-time
order, so the loader sorts a window of messages by publish time before queueing them, as rosbag2 sorts its
read-ahead priority queue: the window holds up to the queue's count and bytes bounds (a message published
earlier than one that left the window already goes out late, at once; a larger read-ahead fixes that). A message
without a publish time (MCAP publish_time 0) counts at its receive time; SQLite3 bags store no publish time at
all, so there both orders are the same. A message published before the pass's start (the bag's first messages:
publish precedes receipt) is due at the start, in its publish order.
"""
from __future__ import annotations

import heapq
import threading
import time
from collections import deque
from collections.abc import Callable, Collection, Iterable, Iterator
from itertools import islice
from typing import Any, Protocol

from baglib.read.reader import BagMessage
from baglib.read.timeline import Timeline
from components.player.decode_worker import Job


class Decoder(Protocol):
    """What the loader asks of a decoder of compressed topics (components/player/decoded_topics.Decoding)."""

    def start_pass(self) -> None: ...

    def submit(self, message: BagMessage) -> Job | None: ...

    def end_pass(self) -> None: ...

    def close(self) -> None: ...


class Queued:
    """A queued message, the bag time it is due at (``time_ns``: its receive or publish time), what the
    playback thread prepared for it (``None``: not yet, or nothing), its decoding (``None``: not a decoded topic)
    and its decoded picture (``None``: none, or not taken yet)."""

    __slots__ = ("decoded", "decoding", "message", "prepared", "ready", "size", "time_ns")

    def __init__(self, message: BagMessage, time_ns: int) -> None:
        self.message = message
        self.time_ns = time_ns
        self.prepared: Any = None
        self.ready = False
        self.decoding: Job | None = None
        self.decoded: Any = None
        self.size = len(message.data) if isinstance(message.data, bytes) else message.data.nbytes

    def add_decoding(self, decoder: Decoder) -> None:
        """Hand the message to its stream's decoder if it is of a decoded topic."""
        self.decoding = decoder.submit(self.message)
        if self.decoding is not None:
            self.size += self.decoding.expected_bytes

    def take_decoded(self) -> None:
        """The compressed object and the picture of a decoded topic's message, waiting for its decoder."""
        assert self.decoding is not None
        self.prepared, self.decoded = self.decoding.wait()
        self.ready = True


class ReadAhead:
    """A loader thread over the bags' timeline; the playback thread ``peek``s and ``pop``s."""

    def __init__(self, reader: Timeline, topics: Collection[str], max_messages: int, max_bytes: int,
                 on_error: Callable[[BaseException], None], decoder: Decoder | None = None,
                 by_publish_time: bool = False) -> None:
        self._reader = reader
        self._decoder = decoder
        self._by_publish_time = by_publish_time
        self._topics = list(topics)
        self._max_messages = max_messages
        self._max_bytes = max_bytes
        self._on_error = on_error
        self._queue: deque[Queued] = deque()
        self._bytes = 0
        self._pass = 0            # bumped by restart(): the loader drops a pass that is no longer wanted
        self._pass_done = True    # the current pass reached its end (or failed)
        self._filled = False      # the current pass filled the queue once (the loader waited for room)
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
            self._filled = False
            self._start_ns, self._stop_ns = start_ns, stop_ns
            self._changed.notify_all()

    def halt(self) -> None:
        """End the current pass and drop the queue (a run ended): the loader and the decoders go idle until the
        next ``restart``."""
        with self._changed:
            self._queue.clear()
            self._bytes = 0
            self._pass += 1
            self._pass_done = True
            self._changed.notify_all()

    def peek(self, timeout: float) -> Queued | None:
        """The next message of the current pass, waiting up to ``timeout`` s for the loader; None at the end
        of the pass, or when the wait timed out (``at_end`` tells which)."""
        with self._changed:
            if not self._queue and not self._pass_done:
                self.starved += 1
                self._changed.wait_for(lambda: self._queue or self._pass_done or self._closed, timeout)
            return self._queue[0] if self._queue else None

    def wait_decoded(self, lead_ns: int, timeout: float) -> bool:
        """With decoded topics: wait until the queue holds the pass's first ``lead_ns`` of bag time (or is full, or
        holds the whole pass) and every picture among them is decoded, at most ``timeout`` s; True if there was
        such a wait (False: nothing is decoded)."""
        if self._decoder is None:
            return False
        deadline = time.monotonic() + timeout
        with self._changed:
            current, until = self._pass, self._start_ns + lead_ns
            self._changed.wait_for(lambda: self._filled or self._pass_done or self._pass != current
                                   or (self._queue and self._queue[-1].time_ns >= until), timeout)
            lead = [item.decoding for item in self._queue if item.decoding is not None and item.time_ns < until]
        for job in lead:
            if not job.wait_done(deadline - time.monotonic()):
                break
        return True

    def head(self, count: int) -> list[Queued]:
        """The first ``count`` queued messages (a snapshot: the loader may append meanwhile)."""
        with self._changed:
            return list(islice(self._queue, count))

    def pop(self) -> None:
        with self._changed:
            if self._queue:
                self._bytes -= self._queue.popleft().size
                self._changed.notify_all()

    @property
    def at_end(self) -> bool:
        """The current pass is fully read and fully taken."""
        with self._changed:
            return self._pass_done and not self._queue

    def close(self) -> None:
        """Stop the loader and the decoders; their threads are gone when this returns."""
        with self._changed:
            self._closed = True
            self._pass += 1
            self._changed.notify_all()
        if self._decoder is not None:
            self._decoder.close()  # a loader waiting for a decoder's free place goes on at once
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
        if self._decoder is not None:
            self._decoder.start_pass()
        items = self._items(messages)
        if self._by_publish_time:
            items = publish_order(items, start_ns, self._max_messages, self._max_bytes)
        try:
            for item in items:
                with self._changed:
                    if not self._filled and self._full(item.size):
                        self._filled = True
                        self._changed.notify_all()
                    self._changed.wait_for(lambda: self._pass != current or not self._full(item.size))
                    if self._pass != current:
                        return
                    self._queue.append(item)
                    self._bytes += item.size
                    self._changed.notify_all()
        finally:
            messages.close()  # type: ignore[attr-defined]  # a generator: releases its files' positions
            if self._decoder is not None:
                self._decoder.end_pass()

    def _items(self, messages: Iterable[BagMessage]) -> Iterator[Queued]:
        """The messages as read (receive-time order), handed to their decoders where a decoder wants them."""
        for message in messages:
            item = Queued(message, message.log_time_ns)
            if self._decoder is not None:
                item.add_decoding(self._decoder)
            yield item

    def _full(self, size: int) -> bool:
        if not self._queue:
            return False  # one message always fits, however big
        return len(self._queue) >= self._max_messages or self._bytes + size > self._max_bytes



def publish_order(items: Iterable[Queued], start_ns: int, max_messages: int, max_bytes: int) -> Iterator[Queued]:
    """``items`` (in receive-time order) sorted by publish time within a window of ``max_messages`` messages
    and ``max_bytes`` bytes (always at least one), equal times in bag order. Each is due at its publish time
    (its receive time if it has none), but never before ``start_ns`` nor before the message sent before it:
    the due times never go back, so one late message does not move the schedule of the rest."""
    window: list[tuple[int, int, Queued]] = []
    size = 0
    floor = start_ns

    def due() -> Queued:
        nonlocal size, floor
        publish_ns, _, item = heapq.heappop(window)
        size -= item.size
        floor = item.time_ns = max(publish_ns, floor)
        return item

    for sequence, item in enumerate(items):
        message = item.message
        heapq.heappush(window, (message.publish_time_ns or message.log_time_ns, sequence, item))
        size += item.size
        while len(window) > max_messages or (size > max_bytes and len(window) > 1):
            yield due()
    while window:
        yield due()
