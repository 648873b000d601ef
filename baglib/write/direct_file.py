"""A write-only file that bypasses the page cache (``O_DIRECT``), for the recorder's big sequential writes.

Why: with buffered writes the kernel spends about 2 CPU seconds per GB copying into and managing the page
cache — more than everything else the recorder does. ``O_DIRECT`` lets the disk read straight from our
memory (a few hundredths of a CPU second per GB). It needs block-aligned buffers, offsets and
sizes, so writes are staged in page-aligned buffers (one memcpy, ~0.1 s/GB) and written a whole number of
blocks at a time. On close the last partial block is written padded and the file truncated to its length.

A large buffer skips the staging copy when its memory and its place in the file fall on the same offset within
a block (:meth:`DirectFile.gap_before` tells a writer how many bytes to put before it to get there): its
unaligned head is staged, and then its whole blocks go to the disk straight from the caller's memory; only the
unaligned tail is staged. For a 1080p frame that removes a 6.2 MB memcpy: about half the CPU per GB of staged
writes, at the disk's throughput.

A file opened with ``gather`` bytes (the recorder's: :data:`GATHER`) gathers whole blocks instead of writing them
one by one: staged blocks and big buffers' own blocks are queued in file order and go to the disk in one
``pwritev`` once ``gather`` bytes are queued, or when the writer asks
(:meth:`write_gathered` when it has no more messages at hand, :meth:`write_through`, :meth:`close`). Why: a
thread returning from a system call needs the GIL back before it can issue the next one, and while other
threads run Python code that takes up to the switch interval (5 ms). With one write per 1080p frame (3.6 ms of
disk time at 1.7 GB/s) and a busy executor, the disk idled for more than half the time (0.6 instead of 1.9 GB/s
in a two-thread measurement); one hand-over per gathered write instead of one per frame gives most of that back.
Gathered writes run on :data:`IN_FLIGHT` (2) I/O threads of the file, each ``pwritev`` at its own offset, so that
when one returns and its thread waits for the GIL the next is in the kernel already (ext4 runs appending direct
writes one after the other anyway) and the writer thread goes on gathering meanwhile. A big buffer is then
referenced, not copied, until it is written: its content must not change before :meth:`write_through` or
:meth:`close` return, which wait for every write. A failed write on an I/O thread is raised by the file's next
call. Without ``gather`` (0), every whole block is written at once, on the calling thread, and a big buffer before
:meth:`write` returns: the caller may reuse it right after.

After a failed write the file takes no more data: :meth:`close` only closes it, so that what the file holds is
what the successful writes put there (the MCAP storage then repairs it).

Filesystems without ``O_DIRECT`` (tmpfs on older kernels, some network filesystems) get a plain buffered file.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import mmap
import os
import queue
import threading
from collections import deque
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

BLOCK = 4096  # a multiple of every logical block size O_DIRECT may require
STAGING = 1024 * 1024  # bytes of one staging buffer (like the 1 MiB buffer of unchunked files)
#: A buffer at least this big is written from the caller's memory when it is aligned (see the module docstring).
IN_PLACE_MIN = 256 * 1024
#: What the recorder gathers into one ``pwritev`` (see the module docstring): five 1080p frames.
GATHER = 32 * 1024 * 1024
#: Gathered writes running at once, each on an I/O thread of the file (see the module docstring).
IN_FLIGHT = 2
#: Most segments one ``pwritev`` takes (Linux: 1024).
IOV_MAX = os.sysconf("SC_IOV_MAX") if "SC_IOV_MAX" in os.sysconf_names else 1024


def address(view: memoryview) -> int:
    """Where the first byte of ``view`` (C-contiguous, read-only or not) lies in memory."""
    import numpy  # imported here: only a writer needs it, and the bag CLI starts faster without it

    return numpy.frombuffer(view, dtype=numpy.uint8).ctypes.data if view.nbytes else 0


class _Staging:
    """One page-aligned staging buffer (anonymous mappings are page-aligned)."""

    def __init__(self) -> None:
        self.map = mmap.mmap(-1, STAGING)
        self.view = memoryview(self.map)

    def close(self) -> None:
        self.view.release()
        with contextlib.suppress(BufferError):  # a view still held (by a traceback): the collector frees it
            self.map.close()


class _Job:
    """One gathered write handed to an I/O thread: the segments, where they go, the staging buffers they use."""

    __slots__ = ("segments", "offset", "buffers", "done", "error")

    def __init__(self, segments: list[memoryview], offset: int, buffers: list[_Staging]) -> None:
        self.segments: list[memoryview] | None = segments
        self.offset = offset
        self.buffers = buffers
        self.done = threading.Event()
        self.error: BaseException | None = None


class DirectFile:
    """The subset of a binary file object the MCAP storage uses: ``write``, ``flush``, ``tell``, ``close``."""

    raw = None  # no separate raw stream to close on failure (cf. io.BufferedWriter)

    def __init__(self, fd: int, gather: int = 0) -> None:
        self._fd = fd
        self._gather = gather
        self._direct = True
        self._failed = False
        self.closed = False
        #: Bytes written from the callers' memory without staging (the tests read it).
        self.in_place = 0
        #: Bytes handed to writes so far: where the next write goes.
        self._submitted = 0
        # Whole blocks waiting for the next write, in file order: slices of staging buffers and of callers' memory.
        self._queue: list[memoryview] = []
        self._queued = 0
        # The staging buffer being filled: bytes [0, _sealed) of it are queued, [_sealed, _staged) are not yet.
        # Its offsets are congruent to the file's modulo BLOCK, so a block boundary of one is one of the other.
        self._current = _Staging()
        self._sealed = 0
        self._staged = 0
        self._full: list[_Staging] = []   # filled staging buffers whose bytes are queued
        self._spare: list[_Staging] = []  # staging buffers free for reuse
        # Gathering: writes go to IN_FLIGHT I/O threads (started at the first write), oldest first.
        self._jobs: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self._threads: list[threading.Thread] = []
        self._in_flight: deque[_Job] = deque()

    def write(self, data: bytes | bytearray | memoryview) -> int:
        self._check_usable()
        source = memoryview(data).cast("B")
        total = len(source)
        if total >= IN_PLACE_MIN and self._direct:
            head = -address(source) % BLOCK
            if (self.tell() + head) % BLOCK == 0:
                self._stage(source[:head])  # ends the staged bytes on a block boundary
                self._seal(self._staged)
                whole = (total - head) // BLOCK * BLOCK
                self._enqueue(source[head:head + whole])
                self.in_place += whole
                source = source[head + whole:]
        self._stage(source)
        return total

    def gap_before(self, data: bytes | bytearray | memoryview, ahead: int) -> int | None:
        """How many bytes (0 to ``BLOCK - 1``) to write before the next ``ahead`` bytes so that ``data``,
        written right after those, goes to the disk from where it is; None when it would be staged anyway
        (too small, or the file is no longer direct)."""
        view = memoryview(data).cast("B")
        if len(view) < IN_PLACE_MIN or not self._direct:
            return None
        return -(self.tell() + ahead - address(view)) % BLOCK

    def tell(self) -> int:
        return self._submitted + self._queued + self._staged - self._sealed

    def flush(self) -> None:
        """Queue every whole staged block (the storage calls this after each chunk): written now, or with the
        next gathered write when the file gathers. Leaves at most one partial block staged."""
        self._check_usable()
        self._seal(self._staged - self._staged % BLOCK)

    def write_gathered(self) -> None:
        """Start writing every whole block gathered so far (the writer has no more data at hand)."""
        self.flush()
        self._write_queue()

    def write_through(self) -> None:
        """Hand every byte written so far to the OS, the last partial block too (zero-padded, written at its
        offset with pwrite and rewritten whole by the next write), so that a crash of the process cannot cut
        a record that was complete before this call. Returns once every write has."""
        self.write_gathered()
        self._wait_all()
        if not self._staged:
            return
        length = self._staged
        if self._direct:
            length = -(-self._staged // BLOCK) * BLOCK
            self._current.view[self._staged:length] = bytes(length - self._staged)
        with self._failing():
            self._write_at([self._current.view[:length]], self._submitted)

    def fileno(self) -> int:
        return self._fd

    def close(self, sync: bool = False) -> None:
        """Write the rest (the last block padded, then the file cut to its length); with ``sync``, fsync
        after the cut, so that a power loss cannot leave the padding behind the file's last record. After a
        failed write, only close the descriptor (once no write of the file is running any more)."""
        if self.closed:
            return
        self.closed = True
        try:
            if not self._failed:
                size, partial = self.tell(), self._staged
                padded = -(-partial // BLOCK) * BLOCK
                self._current.view[partial:padded] = bytes(padded - partial)
                self._staged = padded
                self._seal(padded)
                self._write_queue()
                self._stop_threads()
                self._wait_all()
                if partial:  # the padding is cut off again
                    with self._failing():
                        os.ftruncate(self._fd, size)
                if sync:
                    os.fsync(self._fd)
        finally:
            self._stop_threads()
            with contextlib.suppress(OSError):  # the first error was raised already
                self._wait_all()  # no I/O thread may write to the descriptor once it is closed (and reused)
            os.close(self._fd)
            self._queue.clear()
            for staging in (self._current, *self._full, *self._spare):
                staging.close()

    # --- the queue ---------------------------------------------------------------------------------------
    def _check_usable(self) -> None:
        if self._in_flight and self._in_flight[0].done.is_set():
            self._finish_oldest()  # raises a failed write's error here, at the next call
        if self._failed:
            raise OSError(errno.EIO, "an earlier write to this file failed")

    def _stage(self, source: memoryview) -> None:
        """Copy ``source`` into the staging buffers, queueing each one as it fills."""
        while source:
            take = min(STAGING - self._staged, len(source))
            self._current.view[self._staged:self._staged + take] = source[:take]
            self._staged += take
            source = source[take:]
            if self._staged == STAGING:
                self._seal(STAGING)
                if self._sealed == STAGING:  # still queued (not written by the seal): go on in another buffer
                    self._full.append(self._current)
                    self._current = self._spare.pop() if self._spare else _Staging()
                    self._sealed = self._staged = 0

    def _seal(self, end: int) -> None:
        """Queue the current staging buffer's bytes up to ``end`` (a block boundary)."""
        if end > self._sealed:
            start, self._sealed = self._sealed, end
            self._enqueue(self._current.view[start:end])

    def _enqueue(self, blocks: memoryview) -> None:
        """Queue whole blocks; write the queue once it holds ``gather`` bytes (at once without gathering)."""
        if blocks:
            self._queue.append(blocks)
            self._queued += len(blocks)
        if self._queued >= self._gather:
            self._write_queue()

    def _write_queue(self) -> None:
        """Write everything queued: on this thread at once, or, gathering, on an I/O thread (waiting first while
        IN_FLIGHT writes run). The current staging buffer goes with the write if some of its bytes are queued;
        its other bytes (a partial block, or what was staged since) move to the start of a fresh one."""
        if not self._queue:
            return
        segments, self._queue = self._queue, []
        buffers, self._full = self._full, []
        if self._sealed:
            fresh = self._spare.pop() if self._spare else _Staging()
            kept = self._staged - self._sealed
            fresh.view[:kept] = self._current.view[self._sealed:self._staged]
            buffers.append(self._current)
            self._current, self._sealed, self._staged = fresh, 0, kept
        offset, self._submitted = self._submitted, self._submitted + self._queued
        self._queued = 0
        if not self._gather:
            try:
                with self._failing():
                    self._write_at(segments, offset)
            finally:
                segments.clear()
            self._spare += buffers
            return
        while len(self._in_flight) >= IN_FLIGHT:
            self._finish_oldest()
        if not self._threads:
            self._threads = [threading.Thread(target=_io_thread, args=(self._jobs, self._write_at), daemon=True,
                                              name=f"bag_io:{self._fd}") for _ in range(IN_FLIGHT)]
            for thread in self._threads:
                thread.start()
        job = _Job(segments, offset, buffers)
        self._in_flight.append(job)
        self._jobs.put(job)

    def _stop_threads(self) -> None:
        """Let the I/O threads end once the writes handed to them are done (nothing more is coming): they are
        gone while the file is cut and fsynced."""
        for _ in self._threads:
            self._jobs.put(None)
        self._threads = []

    def _finish_oldest(self) -> None:
        """Wait for the oldest write in flight; take its staging buffers back; raise its error."""
        job = self._in_flight.popleft()
        job.done.wait()
        self._spare += job.buffers
        if job.error is not None:
            self._failed = True
            raise job.error

    def _wait_all(self) -> None:
        """Wait for every write in flight; raise the first error."""
        error: BaseException | None = None
        while self._in_flight:
            try:
                self._finish_oldest()
            except OSError as failure:
                error = error or failure
        if error is not None:
            raise error

    def _write_at(self, segments: list[memoryview], offset: int) -> None:
        """Write ``segments`` in order at ``offset``, which is block-aligned while the file is direct."""
        index = 0
        while index < len(segments):
            try:
                written = os.pwritev(self._fd, segments[index:index + IOV_MAX], offset)
            except OSError as error:
                if error.errno != errno.EINVAL or not self._direct:
                    raise
                # Near a disk or file-size limit the kernel shortens the write to an unaligned length, which
                # O_DIRECT refuses with EINVAL: retry without it, so the real error (ENOSPC, EFBIG) surfaces
                # and everything that still fits is written.
                self._buffered()
                continue
            if written <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            offset += written
            while written:
                size = len(segments[index])
                if written < size:  # a short write: the rest of this segment next
                    segments[index] = segments[index][written:]
                    break
                written -= size
                index += 1
            if index < len(segments) and offset % BLOCK and self._direct:
                self._buffered()  # a short write left the offset unaligned for O_DIRECT

    @contextlib.contextmanager
    def _failing(self) -> Iterator[None]:
        """Mark the file failed when the block raises."""
        try:
            yield
        except BaseException:
            self._failed = True
            raise

    def _buffered(self) -> None:
        fcntl.fcntl(self._fd, fcntl.F_SETFL, fcntl.fcntl(self._fd, fcntl.F_GETFL) & ~os.O_DIRECT)
        self._direct = False


def _io_thread(jobs: queue.SimpleQueue[_Job | None], write_at: Callable[[list[memoryview], int], None]) -> None:
    """An I/O thread of a gathering file: the writes it is handed, until None."""
    while (job := jobs.get()) is not None:
        try:
            assert job.segments is not None
            write_at(job.segments, job.offset)
        except BaseException as error:  # noqa: BLE001 - handed to the file's thread, which raises it
            job.error = error
        finally:
            job.segments = None  # the callers' memory is not held once written
            job.done.set()


def open_exclusive(path: Path, buffering: int, gather: int = 0) -> BinaryIO | DirectFile:
    """Create ``path`` (never overwriting it) for writing: direct I/O where the filesystem allows it, gathering
    ``gather`` bytes per write (:class:`DirectFile`)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_DIRECT", 0)
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as error:
        if error.errno != errno.EINVAL or not getattr(os, "O_DIRECT", 0):
            raise
        # No O_DIRECT on this filesystem. Linux may have created the file before refusing the flag; it is
        # ours (O_EXCL would have failed on an existing one) and still empty.
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        return open(path, "xb", buffering=buffering)  # noqa: SIM115
    return DirectFile(fd, gather)
