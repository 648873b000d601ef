"""The hand-off between the recorder's intake callbacks and its writer thread.

The intake side (the executor, or a publisher's thread for intra-process messages) must never wait on the
disk: it only appends to this cache. The cache holds ``max_cache_size`` bytes in steady state, counting both
queued messages and those the writer holds until it has written them (so the bound is the recorder's whole
buffer, not one half of a double buffer; the writer frees small messages' room a mebibyte at a time, and the
storage may hold up to three ``GATHER`` (3 x 32 MiB) of written messages until its gathered writes are done).
When the writer falls behind (a disk that stalls for longer than the cache lasts), the cache grows into the stall
``reserve`` before anything is dropped; a message that does not fit even then is dropped and counted for its
topic (never silently lost). The backlog (bytes, and how far behind the oldest queued message is) is visible
live. In snapshot mode the cache is a ring
instead: the oldest messages make room (also those received more than ``max_duration`` seconds before the newest,
rosbag2's ``max_cache_duration``: whichever limit is reached first), and nothing is written until a snapshot is
requested. Evictions from the ring are the ring working as asked, not losses: they are counted apart
(``evicted``).
"""
from __future__ import annotations

import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Callable

from sensor_msgs.msg import CompressedImage, Image, Imu, PointCloud2

from baglib.format.cdr_size import serialized_size


@dataclass(slots=True)
class CachedMessage:
    """One received message: a message object (intra-process) or CDR bytes (DDS), with its stamps."""

    topic: str
    payload: Any
    size: int
    log_time_ns: int
    publish_time_ns: int
    #: a latched message written again at the start of a snapshot (record.repeat_transient_local), not received
    repeat: bool = False


#: Size charged for a message whose size cannot be computed: it cannot be serialized either, and the writer
#: drops and reports it (the intake must never raise in a publisher's thread).
UNSIZED = 256


def _image_size(msg: Image) -> int:
    return 64 + len(msg.header.frame_id) + len(msg.encoding) + len(msg.data)


def _compressed_image_size(msg: CompressedImage) -> int:
    return 48 + len(msg.header.frame_id) + len(msg.format) + len(msg.data)


def _imu_size(msg: Imu) -> int:
    """Exact: header (stamp, frame_id) padded to 8, then 37 float64 (quaternion, vectors, covariances)."""
    return 4 + ((13 + len(msg.header.frame_id.encode()) + 7) & ~7) + 296


def _point_cloud2_size(msg: PointCloud2) -> int:
    return 64 + len(msg.header.frame_id) + sum(24 + len(f.name) for f in msg.fields) + len(msg.data)


# The big sensor messages are sized from their buffers without serializing (at most a few bytes of padding
# over the exact size, never under it), and the Imu, which comes at kilohertz rates, exactly; exact types only,
# as in cdr_fast.
_FAST_SIZES: dict[type, Callable[[Any], int]] = {
    Image: _image_size,
    PointCloud2: _point_cloud2_size,
    CompressedImage: _compressed_image_size,
    Imu: _imu_size,
}


def payload_size(payload: Any) -> int:
    """Bytes a payload occupies once serialized: what counts against ``max_cache_size``.

    Exact for CDR bytes and for message objects (so a LaserScan, MarkerArray or Path counts for what it holds,
    not just a ``data`` field); an upper estimate for images and clouds.
    """
    if isinstance(payload, (bytes, bytearray, memoryview)):
        return len(payload)
    try:
        fast = _FAST_SIZES.get(type(payload))
        return fast(payload) if fast is not None else serialized_size(payload)
    except Exception:  # noqa: BLE001 - a broken message: the writer reports it when it fails to serialize it
        return UNSIZED


class MessageCache:
    """A byte-bounded FIFO with per-topic drop counts; ``take_all`` blocks until data or close."""

    def __init__(self, max_bytes: int, ring: bool = False, reserve: int = 0, max_duration: float = 0.0) -> None:
        self.max_bytes = max_bytes
        #: a ring's time bound: messages received this long before the newest make room (0: none)
        self._max_duration_ns = round(max_duration * 1e9) if ring else 0
        self.reserve = 0 if ring else reserve  # a snapshot ring keeps its size: it evicts instead
        self.peak_bytes = 0
        #: how many times the bytes held went above ``max_bytes``, into the reserve
        self.reserve_entries = 0
        self._ring = ring
        self._queue: deque[CachedMessage] = deque()
        self._bytes = 0
        self._closed = False
        self._failed = False  # closed by a storage failure: what is offered after it is lost, and counted
        self.received: Counter[str] = Counter()  # every push accepted or lost, counted under the lock
        self.dropped: Counter[str] = Counter()  # refused because the cache was full
        self.refused: Counter[str] = Counter()  # refused because the recording had failed
        self.evicted: Counter[str] = Counter()
        # The hot paths (push, release) take the bare lock, a C-level context manager; waits use the condition.
        self._mutex = threading.Lock()
        self._condition = threading.Condition(self._mutex)
        self._wake_bytes = 1  # push wakes the writer once this many bytes are queued
        self._last_take = 0.0  # time.monotonic() of the latest take_all

    @property
    def bytes(self) -> int:
        return self._bytes

    def backlog(self) -> tuple[int, int | None]:
        """Bytes held (queued or being written), and the log time of the oldest queued message (None: none)."""
        with self._mutex:
            return self._bytes, (self._queue[0].log_time_ns if self._queue else None)

    def counts(self) -> tuple[Counter[str], Counter[str], Counter[str]]:
        """Copies of (received, dropped, refused), consistent with each other, for another thread to read."""
        with self._mutex:
            return Counter(self.received), Counter(self.dropped), Counter(self.refused)

    def push(self, message: CachedMessage) -> bool | None:
        """Queue a message: True when taken; False when dropped (and counted) because the cache is full or the
        recording failed; None when offered after a :meth:`close` that ended the recording (the bag's cut
        point: the message belongs to no bag, and is not counted)."""
        with self._mutex:
            if self._closed:
                if not self._failed:
                    return None
                self.received[message.topic] += 1
                self.refused[message.topic] += 1
                return False
            self.received[message.topic] += 1
            if self._ring:
                oldest_kept = message.log_time_ns - self._max_duration_ns if self._max_duration_ns else None
                while self._queue and (self._bytes + message.size > self.max_bytes or (
                        oldest_kept is not None and self._queue[0].log_time_ns < oldest_kept)):
                    old = self._queue.popleft()
                    self._bytes -= old.size
                    self.evicted[old.topic] += 1
            elif self._queue and self._bytes + message.size > self.max_bytes + self.reserve:
                self.dropped[message.topic] += 1
                return False
            self._queue.append(message)
            self._bytes += message.size
            if self._bytes > self.max_bytes >= self._bytes - message.size:
                self.reserve_entries += 1
            if self._bytes > self.peak_bytes:
                self.peak_bytes = self._bytes
            if not self._ring and self._bytes >= self._wake_bytes:
                self._condition.notify()
            return True

    def take_all(self, timeout: float | None = None, gather: float = 0.0) -> list[CachedMessage]:
        """Everything queued, waiting up to ``timeout`` for something to arrive (ring caches never wake).

        With ``gather`` (seconds), once something is queued the call waits until ``gather`` has passed since
        the previous take, so that more messages join the batch: the writer is then woken per batch, not per
        message (see recording_session.BATCH_GATHER for what that saves). A quarter of ``max_bytes`` queued or
        a close ends that wait at once, so gathering never risks a drop that taking at once would avoid.
        """
        with self._condition:
            if not self._queue and not self._closed:
                self._condition.wait(timeout)
            if gather and self._queue:
                until = self._last_take + gather
                self._wake_bytes = max(1, self.max_bytes // 4)
                while not self._closed and self._bytes < self._wake_bytes:
                    remaining = until - time.monotonic()
                    if remaining <= 0:
                        break
                    self._condition.wait(remaining)
                self._wake_bytes = 1
            self._last_take = time.monotonic()
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

    def release(self, size: int) -> None:
        """The writer is done with messages of ``size`` bytes: they stop counting against the bound."""
        with self._mutex:
            if not self._ring:  # a ring's bytes were handed over with the snapshot
                self._bytes -= size

    def close(self, failed: bool = False) -> None:
        """The cut point of the bag: what was pushed before is the writer's to write, nothing pushed after is
        taken; wakes the writer for its final flush. After a ``failed`` close (the storage failed) later pushes
        are real losses, counted in ``received`` and ``refused``; after an ordinary one they are not counted."""
        with self._condition:
            self._failed = self._failed or (failed and not self._closed)
            self._closed = True
            self._condition.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed
