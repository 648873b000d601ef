"""One advertised channel's intake: the bounded queue between a ROS subscription and the bridge's thread.

Messages arrive in the publisher's thread (intra-process, inline) or on the executor (raw CDR over DDS); both
only :meth:`ChannelQueue.offer` them, which never blocks and never raises: the container and the recorder never
wait for the bridge. The queue keeps the newest ``depth`` messages (see :data:`INTAKE_DEPTH`), and at most
:data:`MAX_QUEUED_BYTES`: when it is full the oldest is dropped and counted. A channel with a rate limit admits a
message only once ``1 / rate`` seconds (steady clock) have passed since the last one it admitted; the others are
counted as throttled, and never queued nor serialized.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any, Callable

#: Messages a channel's queue holds (at least; more if max_qos_depth says so). The queue is the only buffer
#: between a publication and the bridge's thread, which competes for the GIL with the container's executor:
#: at 200 Hz, a subscription-sized queue of 10 messages is 50 ms, and a loaded machine stalls longer than that.
INTAKE_DEPTH = 100
#: A channel's queue holds at most this many bytes of messages (in-process objects: their ``data`` buffer).
MAX_QUEUED_BYTES = 64 * 1024 * 1024


def message_bytes(message: Any) -> int:
    """Bytes a queued message holds: CDR bytes as they are, an object by its ``data`` buffer plus headers."""
    if isinstance(message, (bytes, bytearray, memoryview)):
        return len(message)
    data = getattr(message, "data", None)
    return 256 + (len(data) if hasattr(data, "__len__") else 0)


class ChannelQueue:
    """The newest messages of one channel, waiting for the bridge's thread; drops and throttling counted."""

    def __init__(self, topic: str, depth: int, rate_hz: float, wake: Callable[[], None],
                 clock: Callable[[], int] = time.time_ns) -> None:
        self.topic = topic
        self.depth = max(depth, 1)
        self.min_interval_ns = int(1e9 / rate_hz) if rate_hz > 0 else 0
        self._wake = wake
        self._clock = clock
        self._queue: deque[tuple[Any, int, int]] = deque()
        self._queued_bytes = 0
        self._next_admit_ns = 0
        self._lock = threading.Lock()
        self.received = 0
        self.dropped = 0
        self.throttled = 0

    def offer(self, message: Any) -> None:
        """Queue ``message`` (an object or CDR bytes) stamped with the receive time (``clock``: the node's, so
        simulated time under ``use_sim_time``); thread-safe, non-blocking."""
        size = message_bytes(message)
        with self._lock:
            self.received += 1
            if self.min_interval_ns:
                now = time.monotonic_ns()
                if now < self._next_admit_ns:
                    self.throttled += 1
                    return
                self._next_admit_ns = now + self.min_interval_ns
            self._queue.append((message, self._clock(), size))
            self._queued_bytes += size
            while len(self._queue) > self.depth or (self._queued_bytes > MAX_QUEUED_BYTES and len(self._queue) > 1):
                self._queued_bytes -= self._queue.popleft()[2]
                self.dropped += 1
        self._wake()

    def take(self) -> tuple[Any, int] | None:
        """The oldest queued message and its receive time (ns), or None."""
        with self._lock:
            if not self._queue:
                return None
            message, received_ns, size = self._queue.popleft()
            self._queued_bytes -= size
        return message, received_ns

    def clear(self) -> None:
        """Forget what is queued (the last client left): nothing of it is sent any more."""
        with self._lock:
            self._queue.clear()
            self._queued_bytes = 0

    def __len__(self) -> int:
        return len(self._queue)
