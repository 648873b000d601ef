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

Apart from that tuning, :func:`release_free_memory` gives the free memory malloc keeps back to the system: after
a component held much more memory than usual for a while (a recorder's backlog during a disk stall), glibc keeps
the freed heap memory for reuse, and the container would go on showing that peak as its resident size.
"""
from __future__ import annotations

import ctypes
import os
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


def release_free_memory() -> bool:
    """``malloc_trim(0)``: return the free memory of every malloc arena to the system (pages inside free chunks
    too, not only the top of the heap). It holds each arena's lock while it walks it (about 40 ms per GB freed on
    the reference machine): for after a peak, not for a hot path. False where malloc is not glibc's."""
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return False
    trim.argtypes = (ctypes.c_size_t,)
    trim(0)
    return True


def resident_bytes() -> int:
    """This process's resident set size (``/proc/self/statm``), in bytes; 0 where there is no such file."""
    try:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        return 0
