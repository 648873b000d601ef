"""The free-space guard: a recorder stops cleanly, with a finalized bag, before its disk is full.

A full disk in the middle of a chunk costs the chunk and leaves the machine without room for anything else
(logs, the OS itself). So the recorder keeps ``storage.min_free_space`` bytes free: it refuses to start below
it and, once the free space drops below it while recording, ends the session as a storage failure, which
finalizes the bag with what was written. The guard is checked after every batch the writer thread writes
(``statvfs`` costs microseconds), so the margin only has to hold what one batch can add.

A recorder that uploads its bags gives the guard a way to make room first (:attr:`DiskGuard.reclaim`): files
already verified in the store are deleted, oldest first, before the recording is stopped for want of space.
"""
from __future__ import annotations

import errno
import os
import time
from collections.abc import Callable
from pathlib import Path

from baglib.write.writer import BagWriteError

#: Rate samples older than this are forgotten: the estimate follows the current write rate.
RATE_WINDOW = 5.0
#: Room a reclaim makes beyond the minimum, so that it is not repeated at every batch.
RECLAIM_HEADROOM = 64 * 1024 * 1024


def free_bytes(path: Path) -> int:
    """Bytes an unprivileged writer may still use on the filesystem of ``path`` (or of its nearest ancestor)."""
    for candidate in (path, *path.parents):
        try:
            info = os.statvfs(candidate)
        except FileNotFoundError:
            continue
        return info.f_bavail * info.f_frsize
    raise FileNotFoundError(errno.ENOENT, "no existing directory on the path", str(path))


class DiskGuard:
    """Watches the free space of a bag's filesystem while it is written; estimates the time left."""

    def __init__(self, path: Path, min_free: int) -> None:
        """Raise ValueError naming storage.min_free_space if the bag at ``path`` starts with less free."""
        self.path = path
        self.min_free = min_free
        self.free = free_bytes(path)
        self._samples: list[tuple[float, int]] = []  # (monotonic time, bytes written)
        #: Frees at least the bytes asked for if it can (deleting what is safe to delete); returns bytes freed.
        self.reclaim: Callable[[int], int] | None = None
        if self.free < min_free:
            raise ValueError(f"parameter 'storage.min_free_space': only {self.free} bytes are free on the disk of "
                             f"{path}, less than the {min_free} bytes to keep free: not recording")

    def check(self, bytes_written: int) -> None:
        """Update the free space and the write rate; raise BagWriteError(ENOSPC) below the minimum."""
        now = time.monotonic()
        self.free = free_bytes(self.path)
        self._samples.append((now, bytes_written))
        if self.min_free and self.free < self.min_free and self.reclaim is not None:
            if self.reclaim(self.min_free + RECLAIM_HEADROOM - self.free):
                self.free = free_bytes(self.path)
        while len(self._samples) > 2 and now - self._samples[0][0] > RATE_WINDOW:
            self._samples.pop(0)
        if self.min_free and self.free < self.min_free:
            raise BagWriteError(errno.ENOSPC, f"free disk space fell to {self.free} bytes, below "
                                f"storage.min_free_space ({self.min_free} bytes): recording stopped, the bag "
                                "is finalized", str(self.path))

    @property
    def write_rate(self) -> float:
        """Bytes per second written over the last few seconds."""
        if len(self._samples) < 2:
            return 0.0
        (start, first), (end, last) = self._samples[0], self._samples[-1]
        return (last - first) / (end - start) if end > start else 0.0

    @property
    def seconds_left(self) -> float | None:
        """Seconds until the free space reaches the minimum at the current write rate (None: not writing)."""
        rate = self.write_rate
        return max(0.0, (self.free - self.min_free) / rate) if rate > 0 else None
