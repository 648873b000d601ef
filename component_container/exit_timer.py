"""A bound on the last step of a process, destroying its ROS participant, that holds even when Python cannot run.

Why: Fast DDS 2.14 and 3.2 can livelock destroying a participant (docs/limitations.md). rclpy destroys a node
holding the GIL, and Fast DDS destroys the participant with the last node, so a thread stuck there stops every
Python thread of the process: a ``join`` with a timeout, a ``threading.Timer`` and signal handlers never run
again. What still runs is native: faulthandler's watchdog thread prints every thread's Python stack, and a POSIX
timer (``timer_create`` with ``SIGEV_THREAD``: glibc runs its function on a thread of its own) calls ``_exit``
with the status the process was to end with, which it takes as the timer's value.
"""
from __future__ import annotations

import contextlib
import ctypes
import faulthandler
import sys
from typing import Callable

CLOCK_MONOTONIC = 1
SIGEV_THREAD = 2
#: s: after the stacks are printed, before the exit
STACKS_MARGIN = 0.2


class _SigEvent(ctypes.Structure):
    """``struct sigevent`` (glibc, 64 bytes) for SIGEV_THREAD."""

    _fields_ = [("value", ctypes.c_void_p), ("signo", ctypes.c_int), ("notify", ctypes.c_int),
                ("function", ctypes.c_void_p), ("attributes", ctypes.c_void_p), ("_pad", ctypes.c_int * 8)]


class _TimeSpec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _ITimerSpec(ctypes.Structure):
    _fields_ = [("interval", _TimeSpec), ("value", _TimeSpec)]


class ExitTimer:
    """Ends the process with ``status`` (``_exit``: no clean-up, no flush) after ``seconds``, unless cancelled."""

    def __init__(self, seconds: float, status: int) -> None:
        self._libc = ctypes.CDLL(None, use_errno=True)
        event = _SigEvent(value=status, notify=SIGEV_THREAD,
                          function=ctypes.cast(self._libc._exit, ctypes.c_void_p).value)
        self._timer = ctypes.c_void_p()
        if self._libc.timer_create(CLOCK_MONOTONIC, ctypes.byref(event), ctypes.byref(self._timer)) != 0:
            raise OSError(ctypes.get_errno(), "timer_create failed")
        whole = int(seconds)
        expiry = _ITimerSpec(value=_TimeSpec(whole, int((seconds - whole) * 1e9)))
        if self._libc.timer_settime(self._timer, 0, ctypes.byref(expiry), None) != 0:
            error = ctypes.get_errno()
            self.cancel()
            raise OSError(error, "timer_settime failed")

    def cancel(self) -> None:
        self._libc.timer_delete(self._timer)


def end_within(limit: float, status: int, teardown: Callable[[], None]) -> None:
    """Run ``teardown`` (destroying nodes and rclpy contexts); if it has not returned after ``limit`` s, print
    every thread's Python stack on stderr (faulthandler's "Timeout" report) and end the process with ``status``.
    Python's own buffered output is flushed first: ``_exit`` drops it."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    faulthandler.dump_traceback_later(limit, exit=False, file=sys.__stderr__)
    timer = ExitTimer(limit + STACKS_MARGIN, status)
    try:
        teardown()
    finally:
        timer.cancel()
        faulthandler.cancel_dump_traceback_later()
