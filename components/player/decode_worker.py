"""One decoded stream's thread: its messages decoded in the order they were read, ahead of playback, a few at a
time.

The player's read-ahead thread reads the bag and hands each message of a decoded topic to that topic's
:class:`StreamWorker` (:meth:`~StreamWorker.submit`) instead of decoding it itself; the playback thread waits for
the :class:`Job` only when the message is due. So every stream decodes on a thread of its own (the codecs release
the GIL: streams decode on all cores), one stream's messages strictly in turn (a video decoder needs every access
unit in order), and the reader goes on with the other topics meanwhile.

Bounds: at most ``depth`` messages of a stream are submitted and not yet decoded (:meth:`submit` waits for a free
place), so a stream whose decoder falls behind holds the reader back instead of piling up work; the pictures
decoded and not yet played are in the read-ahead queue, under its byte bound.

Priority: the threads run :data:`NICE` steps below the thread that starts them (Linux's nice value, which is per
thread; the threads FFmpeg starts from a decoder inherit it). Their work is done ahead of time, the playback thread's
is due at a given moment. At the same priority, a few streams' decoders (and FFmpeg's threads) held every core just
when the playback thread woke for a due message or published the next ones, and it waited for a core instead of
for its schedule; a little lower, the scheduler hands it a core at once, and the decoders still get most of the
CPU, since playback uses a fraction of one core. Two streams together weigh about as much as one thread of normal
priority: the share the single decoding thread had before against other busy processes.

A thread lives from the first message of a pass to the end of that pass's work (:meth:`end_pass`: it leaves once
its jobs are done), and :meth:`close` cancels what is left and joins it: a player that stops or unloads leaves no
decoding thread behind.
"""
from __future__ import annotations

import os
import sys
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

from baglib.read.reader import BagMessage

#: How long close() waits for a decode that is under way.
JOIN_TIMEOUT_S = 5.0
#: How many nice steps below the thread that starts it a decoding thread runs (see the module docstring).
NICE = 3


class Job:
    """One message handed to a stream's decoder; its result is taken by the playback thread when it is due."""

    __slots__ = ("_done", "_error", "_result", "expected_bytes", "message", "new_pass")

    def __init__(self, message: BagMessage, expected_bytes: int, new_pass: bool) -> None:
        self.message = message
        self.expected_bytes = expected_bytes  # what its picture will take (the stream's last one): the queue's bytes
        self.new_pass = new_pass              # the first of a pass: the decoder starts afresh
        self._done = threading.Event()
        self._result: tuple[Any, Any] = (None, None)
        self._error: BaseException | None = None

    def finish(self, result: tuple[Any, Any] = (None, None), error: BaseException | None = None) -> None:
        """Done (or cancelled: no result), and whoever waits goes on."""
        self._result, self._error = result, error
        self._done.set()

    def wait_done(self, timeout: float) -> bool:
        """Whether it is done (or cancelled) within ``timeout`` s."""
        return self._done.wait(max(timeout, 0.0))

    def wait(self) -> tuple[Any, Any]:
        """The result once done: the compressed message object and its picture (both None: cancelled; the
        picture None: skipped or failed, counted by the stream). Re-raises what the decoding raised."""
        self._done.wait()
        if self._error is not None:
            raise self._error
        return self._result


class StreamWorker:
    """One stream's decoding thread: :meth:`submit`, :meth:`end_pass`, :meth:`close` (see module docstring)."""

    def __init__(self, name: str, run: Callable[[Job], tuple[Any, Any]], depth: int) -> None:
        self.name = name
        self._run = run
        self._depth = depth
        self._jobs: deque[Job] = deque()
        self._running = 0                 # 1 while a job is being decoded
        self._thread: threading.Thread | None = None
        self._leaving = False             # the thread found nothing to do after end_pass and is ending
        self._finishing = False           # the pass ended: leave once the jobs are done
        self._closed = False
        self._changed = threading.Condition()

    @property
    def in_flight(self) -> int:
        """Messages submitted and not decoded yet (at most ``depth``)."""
        with self._changed:
            return len(self._jobs) + self._running

    def submit(self, job: Job) -> None:
        """Queue ``job``, waiting while ``depth`` are in flight; on a closed worker it is cancelled at once."""
        with self._changed:
            self._changed.wait_for(lambda: self._closed or len(self._jobs) + self._running < self._depth)
            if self._closed:
                job.finish()
                return
            self._jobs.append(job)
            self._finishing = False
            if self._thread is None or self._leaving:
                if self._thread is not None:
                    self._thread.join()  # it holds nothing any more and is returning
                self._leaving = False
                self._thread = threading.Thread(target=self._work, name=self.name, daemon=True)
                self._thread.start()
            self._changed.notify_all()

    def cancel_pending(self) -> None:
        """Drop the jobs not started yet (a new pass: nobody will take their results)."""
        with self._changed:
            dropped = list(self._jobs)
            self._jobs.clear()
            self._changed.notify_all()
        for job in dropped:
            job.finish()

    def end_pass(self) -> None:
        """No more jobs for now: the thread leaves once the submitted ones are done."""
        with self._changed:
            self._finishing = True
            self._changed.notify_all()

    def close(self) -> None:
        """Cancel what is not started, let the current decode end, join the thread; later submits are cancelled."""
        with self._changed:
            self._closed = True
        self.cancel_pending()
        with self._changed:
            thread = self._thread
        if thread is not None:
            thread.join(JOIN_TIMEOUT_S)

    def _work(self) -> None:
        lower_priority(NICE)
        while True:
            with self._changed:
                self._changed.wait_for(lambda: self._jobs or self._finishing or self._closed)
                if not self._jobs:
                    self._leaving = True
                    return
                job = self._jobs.popleft()
                self._running = 1
            try:
                result = self._run(job)
            except Exception as exc:  # noqa: BLE001 - handed to the job's taker, the stream goes on
                job.finish(error=exc)
            else:
                job.finish(result)
            finally:
                with self._changed:
                    self._running = 0
                    self._changed.notify_all()


def lower_priority(steps: int) -> None:
    """Run the calling thread ``steps`` nice values lower than it runs now (at most 19). Only on Linux, where the
    value is the thread's own (elsewhere it would be the whole process's); a system that refuses leaves it as it is."""
    if sys.platform != "linux":
        return
    thread = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, thread, min(os.getpriority(os.PRIO_PROCESS, thread) + steps, 19))
    except OSError:
        pass  # the stream still decodes, at the priority of the rest
