"""Keep an encoder library from making threads real-time.

SVT-AV1, run as root, creates every thread it starts with ``SCHED_FIFO`` at priority 99, and switches the thread
that opens an encoder to it as well ("Failed to set thread priority" is its only word about it). Every thread
created afterwards by those threads inherits it: a container that loaded an AV1 encoder then had Fast DDS's
threads spinning at real-time priority, starving every other process on the machine. SVT-AV1 starts all its
threads while the codec opens (its thread count stays the same while it encodes); undoing their scheduling once
the open returned was not enough: after the first frame, most were real-time again.

:func:`without_sys_nice` runs a call with ``CAP_SYS_NICE`` taken out of the calling thread's effective
capabilities (Linux capabilities are per thread, and a new thread starts with its creator's): a real-time request
then fails with EPERM, on which SVT-AV1 creates the thread without it, and the threads created meanwhile lack the
capability for good, so no later request of theirs succeeds either; afterwards it puts the capability back in the
calling thread. :func:`ordinary_scheduling`, for opening a codec, also undoes any scheduling change that got
through anyway.
"""
from __future__ import annotations

import contextlib
import ctypes
import os
from collections.abc import Iterator

REAL_TIME = (os.SCHED_FIFO, os.SCHED_RR)
CAP_SYS_NICE = 23
_CAPABILITY_VERSION_3 = 0x20080522


class _CapHeader(ctypes.Structure):
    _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]


class _CapData(ctypes.Structure):
    _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32), ("inheritable", ctypes.c_uint32)]


_libc = ctypes.CDLL(None, use_errno=True)


def _capabilities() -> tuple[_CapHeader, ctypes.Array] | None:
    """The calling thread's capability sets (pid 0: this thread), or None where they cannot be read."""
    header, data = _CapHeader(_CAPABILITY_VERSION_3, 0), (_CapData * 2)()
    return (header, data) if _libc.capget(ctypes.byref(header), data) == 0 else None


@contextlib.contextmanager
def without_sys_nice() -> Iterator[None]:
    """Run the block without CAP_SYS_NICE in this thread's effective set (if it had it), then restore it."""
    found = _capabilities()
    if found is None or not found[1][0].effective & (1 << CAP_SYS_NICE):
        yield
        return
    header, data = found
    data[0].effective &= ~(1 << CAP_SYS_NICE)
    dropped = _libc.capset(ctypes.byref(header), data) == 0
    try:
        yield
    finally:
        if dropped:
            data[0].effective |= 1 << CAP_SYS_NICE
            _libc.capset(ctypes.byref(header), data)


def _threads() -> dict[int, tuple[int, os.sched_param]]:
    policies = {}
    for name in os.listdir("/proc/self/task"):
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            tid = int(name)
            policies[tid] = (os.sched_getscheduler(tid), os.sched_getparam(tid))
    return policies


@contextlib.contextmanager
def ordinary_scheduling() -> Iterator[None]:
    """Run the block unable to make threads real-time; undo any scheduling change it still made."""
    before = _threads()
    try:
        with without_sys_nice():
            yield
    finally:
        for tid, (policy, param) in _threads().items():
            if tid in before and (policy, param.sched_priority) != (before[tid][0], before[tid][1].sched_priority):
                restore = before[tid]
            elif tid not in before and policy in REAL_TIME:
                restore = (os.SCHED_OTHER, os.sched_param(0))
            else:
                continue
            with contextlib.suppress(OSError):
                os.sched_setscheduler(tid, *restore)
