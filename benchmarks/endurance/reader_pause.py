"""The soak's file reader steps aside while the recorder is behind.

Reading every file back (a second stream of 405 MB/s, through the page cache) competes with the recorder for the
disk and the CPUs: on a 2-core machine that others use too, a stretch of their load on top of it can keep the
recorder behind for longer than its stall reserve lasts. The reader is the soak's own load, not the system under
test, so it is stopped (SIGSTOP) while the recorder's backlog is beyond its cache and continued (SIGCONT) once
the backlog is down to a quarter of it; the files it has not read wait for it, hard-linked.
"""
from __future__ import annotations

import os
import signal
import time
from typing import Optional


class ReaderPause:
    """Stops and continues the worker process ``pid`` by the recorder's backlog."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.pauses = 0
        self.paused_s = 0.0
        self._since: Optional[float] = None

    def update(self, backlog_bytes: int, cache_bytes: int) -> None:
        if self._since is None and backlog_bytes > cache_bytes:
            os.kill(self.pid, signal.SIGSTOP)
            self._since = time.monotonic()
            self.pauses += 1
        elif self._since is not None and backlog_bytes <= cache_bytes // 4:
            self.resume()

    def resume(self) -> None:
        if self._since is not None:
            os.kill(self.pid, signal.SIGCONT)
            self.paused_s += time.monotonic() - self._since
            self._since = None
