"""A byte-rate limit (``upload.max_rate``): a token bucket the uploader draws from before each request."""
from __future__ import annotations

import threading
import time


class Throttle:
    """At most ``rate`` bytes per second on average (0: unlimited), with a burst of one second's worth.

    A request larger than the burst waits until its bytes are earned, so the rate holds at part granularity.
    ``wait`` returns early, False, when ``stop`` is set.
    """

    def __init__(self, rate: float, stop: threading.Event | None = None) -> None:
        self.rate = rate
        self._stop = stop or threading.Event()
        self._tokens = rate
        self._last = time.monotonic()

    def wait(self, size: int) -> bool:
        if self.rate <= 0:
            return not self._stop.is_set()
        now = time.monotonic()
        self._tokens = min(self.rate, self._tokens + (now - self._last) * self.rate) - size
        self._last = now
        if self._tokens < 0 and self._stop.wait(-self._tokens / self.rate):
            return False
        return not self._stop.is_set()
