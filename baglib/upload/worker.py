"""The upload process: ``python -m baglib.upload.worker JOURNAL [--max-rate BYTES_PER_S]``.

A recorder's container starts one per journal (per directory of bags; see
components/recorder/upload_process.py): the uploads then never take the recorder's CPU time or GIL, and they go
on after the recorder is unloaded. It runs at a lower CPU priority (``nice`` +10) and holds at most
``transfer.PARTS_IN_FLIGHT`` parts in memory. What it is told:

* a byte on its standard input: the journal has something new;
* end of its input: nothing more will be queued: it finishes the queue, then exits;
* SIGTERM, or its parent's death (the container exited, even by SIGKILL): it stops between two requests (a
  request in flight gets STOP_GRACE seconds); the journal keeps what it had not done, for the next recorder over
  that directory or ``bag upload --resume``.

One process works on a journal at a time (an exclusive lock beside it). After a failure it retries with a
back-off from 1 to 30 seconds, or at once when woken.
"""
from __future__ import annotations

import argparse
import fcntl
import os
import signal
import sys
import threading
import time
from pathlib import Path

from baglib.upload.journal import UploadJournal
from baglib.upload.uploader import Uploader

#: Seconds between retries after a failure: doubled from the first to the last.
FIRST_RETRY = 1.0
LAST_RETRY = 30.0
#: The CPU priority the uploads run at (added to the container's).
NICENESS = 10
#: Seconds between two looks at whether the parent process is still there.
PARENT_POLL = 0.5
#: Seconds a request in flight may take to end once the process is told to stop; then it exits anyway (what the
#: journal holds is consistent at any moment: it is built for SIGKILL).
STOP_GRACE = 2.0


def lock_journal(journal: Path, wait: bool) -> int | None:
    """An exclusive lock on ``journal`` (its ``.lock`` file): the fd holding it, or None if another process has it
    and ``wait`` is False."""
    fd = os.open(f"{journal}.lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


class _Signals:
    """What the process is told, as events: ``wake`` (look at the queue), ``finishing`` (end of input) and
    ``stop`` (stop between two requests)."""

    def __init__(self) -> None:
        self.wake, self.finishing, self.stop = threading.Event(), threading.Event(), threading.Event()
        self._parent = os.getppid()
        # SIGTERM is taken by a thread of its own (sigwait), blocked everywhere else: a Python handler setting an
        # Event could deadlock on the Event's lock if the signal came while the main thread held it.
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
        threading.Thread(target=self._wait_for_sigterm, name="sigterm", daemon=True).start()
        threading.Thread(target=self._read_input, name="input", daemon=True).start()
        threading.Thread(target=self._watch_parent, name="parent", daemon=True).start()

    def _stop(self) -> None:
        self.stop.set()
        self.wake.set()
        time.sleep(STOP_GRACE)  # the main thread ends the process first unless a request holds it
        os._exit(0)

    def _wait_for_sigterm(self) -> None:
        signal.sigwait({signal.SIGTERM})
        self._stop()

    def _read_input(self) -> None:
        while os.read(sys.stdin.fileno(), 4096):
            self.wake.set()
        self.finishing.set()
        self.wake.set()

    def _watch_parent(self) -> None:
        while not self.stop.wait(PARENT_POLL):
            if os.getppid() != self._parent:
                self._stop()
                return


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m baglib.upload.worker")
    parser.add_argument("journal", type=Path)
    parser.add_argument("--max-rate", type=float, default=0.0, help="bytes per second (0: unlimited)")
    args = parser.parse_args(argv)
    os.nice(NICENESS)
    signals = _Signals()
    while lock_journal(args.journal, wait=False) is None:  # another process uploads from this journal
        if signals.stop.wait(0.5):
            return 0
    journal = UploadJournal(args.journal)
    uploader = Uploader(journal, args.max_rate, signals.stop)
    retry = FIRST_RETRY
    while not signals.stop.is_set():
        signals.wake.clear()
        failure = uploader.drain()
        if failure is None:
            if signals.finishing.is_set():
                break
            retry = FIRST_RETRY
            signals.wake.wait()
        else:
            signals.wake.wait(retry)
            retry = min(LAST_RETRY, retry * 2)
    journal.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
