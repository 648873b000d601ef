"""Large buffers from reused memory: glibc's malloc tuned so that a deserialized camera frame lands in pages
the process already has.

By default glibc serves a 6 MB request from fresh ``mmap`` pages and returns them when freed; the first write
into each 4 KiB page is then a page fault. A player deserializes every frame into a new buffer (the message
belongs to its subscribers), so a 1080p rgb8 frame costs ~1500 faults, several ms of copying *while holding
the GIL*: measured on the S1 replay (benchmarks/replay_bench.py --quick, in-process, rate 1), the publish-time
error p99 was 9.9 ms with the default and 1.45 ms with a 64 MiB mmap and 1 GiB trim threshold, and the
container's CPU 2.6 s against 1.7 s (the 32 MiB trim threshold below gave 2.8 ms on the current player, in the
range of the larger one). Raising the mmap threshold makes such buffers come from the heap, and raising the
trim threshold keeps freed heap memory for the next frame instead of giving it back at once.
"""
from __future__ import annotations

import ctypes
import threading

#: mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Requests below this come from the heap (glibc's own dynamic threshold stops at 32 MiB).
MMAP_THRESHOLD = 64 * 1024 * 1024
#: Free heap memory kept for reuse before the top of the heap is returned to the system: a few frames (more
#: would show as a container that never gives memory back: the fuzz test bounds RSS growth at 50 MiB).
TRIM_THRESHOLD = 32 * 1024 * 1024

_lock = threading.Lock()
_applied = False


def reuse_large_buffers() -> bool:
    """Apply the thresholds once per process (later calls do nothing); False where malloc is not glibc's."""
    global _applied
    with _lock:
        if _applied:
            return True
        try:
            mallopt = ctypes.CDLL(None).mallopt
        except (OSError, AttributeError):
            return False
        mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
        _applied = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD,
                                                                                      TRIM_THRESHOLD))
        return _applied
