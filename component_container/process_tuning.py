"""Process-wide tuning for low-latency replay, applied by the container when it is told to (``--low-latency``),
never by a component behind the other components' backs.

Two settings of the whole process:

* **CPython's switch interval** at most :data:`SWITCH_INTERVAL`. A thread that wakes up needs the GIL, and a
  busy thread (a deserializing read-ahead, an executor) hands it over only when the interval runs out: with the
  default 5 ms a due message can wait up to 5 ms, which no replay schedule under 2 ms p99 survives. The cost:
  more GIL hand-overs for every thread of the process, so CPU-bound components run a little slower.
* **glibc malloc thresholds** (:data:`MMAP_THRESHOLD`, :data:`TRIM_THRESHOLD`). By default glibc serves a 6 MB
  request from fresh ``mmap`` pages and returns them when freed; the first write into each 4 KiB page is then a
  page fault. A player deserializes every frame into a new buffer (the message belongs to its subscribers), so
  a 1080p rgb8 frame costs about 1500 faults, several ms of copying while holding the GIL. Raising the mmap
  threshold makes such buffers come from the heap, and raising the trim threshold keeps freed heap memory for
  the next frame instead of giving it back at once. The cost: the process keeps up to TRIM_THRESHOLD of free
  heap memory.

``components::Player`` asks for this in its documentation and warns at load when the container runs without
it; ``ipc-component bag play`` starts its container with it.
"""
from __future__ import annotations

import ctypes
import sys
import threading
from dataclasses import dataclass

#: Switch interval (s) under --low-latency.
SWITCH_INTERVAL = 0.0002
#: mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Requests below this come from the heap (glibc's own dynamic threshold stops at 32 MiB).
MMAP_THRESHOLD = 64 * 1024 * 1024
#: Free heap memory kept for reuse before the top of the heap is returned to the system: a few frames (more
#: would show as a container that never gives memory back).
TRIM_THRESHOLD = 32 * 1024 * 1024


@dataclass(frozen=True)
class Tuning:
    """What :func:`apply_low_latency` changed."""

    switch_interval: float
    malloc_thresholds: bool   # False where malloc is not glibc's


_lock = threading.Lock()
_applied: Tuning | None = None


def apply_low_latency() -> Tuning:
    """Apply both settings to this process (once; later calls return the first result)."""
    global _applied
    with _lock:
        if _applied is None:
            sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL))
            _applied = Tuning(sys.getswitchinterval(), _set_malloc_thresholds())
        return _applied


def low_latency() -> Tuning | None:
    """The tuning this process runs with, or None if it was not asked for."""
    return _applied


def _set_malloc_thresholds() -> bool:
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
