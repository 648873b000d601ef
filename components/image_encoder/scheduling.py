"""Keep an encoder library from changing the process's scheduling.

SVT-AV1, run as root, switches the thread that opens an encoder, and the threads it starts, to real-time
``SCHED_FIFO`` at priority 99 ("Failed to set thread priority" is its only word about it). Every thread created
afterwards by those threads inherits it: a container that loaded an AV1 encoder then had Fast DDS's threads
spinning at real-time priority, starving every other process on the machine. :func:`unchanged_scheduling`
puts back what each thread had before, and ordinary scheduling on the threads the library started.
"""
from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

REAL_TIME = (os.SCHED_FIFO, os.SCHED_RR)


def _threads() -> dict[int, tuple[int, os.sched_param]]:
    policies = {}
    for name in os.listdir("/proc/self/task"):
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            tid = int(name)
            policies[tid] = (os.sched_getscheduler(tid), os.sched_getparam(tid))
    return policies


@contextlib.contextmanager
def unchanged_scheduling() -> Iterator[None]:
    """Run the block, then undo any scheduling change it made to the process's threads."""
    before = _threads()
    try:
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
