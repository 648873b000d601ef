"""A write-only file that bypasses the page cache (``O_DIRECT``), for the recorder's big sequential writes.

Why: with buffered writes the kernel spends about 2 CPU seconds per GB copying into and managing the page
cache — more than everything else the recorder does. ``O_DIRECT`` lets the disk read straight from our
memory (a few hundredths of a CPU second per GB). It needs block-aligned buffers, offsets and
sizes, so writes are staged in a page-aligned buffer (one memcpy, ~0.1 s/GB) and written a whole number of
blocks at a time. On close the last partial block is written padded and the file truncated to its length.

A large buffer skips the staging copy when its memory and its place in the file fall on the same offset within
a block (:meth:`DirectFile.gap_before` tells a writer how many bytes to put before it to get there): its
unaligned head is staged, the staged blocks written, and then its whole blocks go to the disk straight from
the caller's memory; only the unaligned tail is staged. For a 1080p frame that removes a 6.2 MB memcpy, and
one write replaces six 1 MiB ones: about half the CPU per GB of staged writes, at the disk's throughput.

Filesystems without ``O_DIRECT`` (tmpfs on older kernels, some network filesystems) get a plain buffered file.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import mmap
import os
from pathlib import Path
from typing import BinaryIO

BLOCK = 4096  # a multiple of every logical block size O_DIRECT may require
STAGING = 1024 * 1024  # bytes staged before a direct write (like the 1 MiB buffer of unchunked files)
#: A buffer at least this big is written from the caller's memory when it is aligned (see the module docstring).
IN_PLACE_MIN = 256 * 1024


def address(view: memoryview) -> int:
    """Where the first byte of ``view`` (C-contiguous, read-only or not) lies in memory."""
    import numpy  # imported here: only a writer needs it, and the bag CLI starts faster without it

    return numpy.frombuffer(view, dtype=numpy.uint8).ctypes.data if view.nbytes else 0


class DirectFile:
    """The subset of a binary file object the MCAP storage uses: ``write``, ``flush``, ``tell``, ``close``."""

    raw = None  # no separate raw stream to close on failure (cf. io.BufferedWriter)

    def __init__(self, fd: int) -> None:
        self._fd = fd
        self._staging = mmap.mmap(-1, STAGING)  # anonymous mappings are page-aligned
        self._view = memoryview(self._staging)
        self._staged = 0
        self._flushed = 0
        self._direct = True
        self.closed = False
        #: Bytes written from the callers' memory without staging (the tests read it).
        self.in_place = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        source = memoryview(data).cast("B")
        total = len(source)
        if total >= IN_PLACE_MIN and self._direct:
            head = -address(source) % BLOCK
            if (self.tell() + head) % BLOCK == 0:
                self._stage(source[:head])  # ends the staged bytes on a block boundary
                if self._staged:
                    self._write_staged(self._staged)
                whole = (total - head) // BLOCK * BLOCK
                self._write_out(source[head:head + whole])
                self._flushed += whole
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
        return self._flushed + self._staged

    def _stage(self, source: memoryview) -> None:
        """Copy ``source`` into the staging buffer, writing it out each time it is full."""
        while source:
            take = min(STAGING - self._staged, len(source))
            self._view[self._staged:self._staged + take] = source[:take]
            self._staged += take
            source = source[take:]
            if self._staged == STAGING:
                self._write_staged(STAGING)

    def _write_out(self, view: memoryview) -> None:
        """Write all of ``view`` at the file offset, which is block-aligned while the file is direct."""
        done = 0
        while done < len(view):
            try:
                written = os.write(self._fd, view[done:])
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
            done += written
            if done < len(view) and (self._flushed + done) % BLOCK:
                self._buffered()  # a short write left the offset unaligned for O_DIRECT

    def _write_staged(self, length: int) -> None:
        """Write the first ``length`` staged bytes (a whole number of blocks; past the staged end at close)."""
        with self._view[:length] as staged:  # released even when the write fails: close() must unmap
            self._write_out(staged)
        kept = max(0, self._staged - length)
        if kept:  # a partial block stays staged, moved to the start of the (aligned) buffer
            self._view[:kept] = self._view[length:self._staged]
        self._flushed += self._staged - kept
        self._staged = kept

    def flush(self) -> None:
        """Write every whole staged block now (the storage calls this after each chunk), so a failure
        later loses at most the unfinished chunk and one partial block, as with a buffered file."""
        aligned = self._staged - self._staged % BLOCK
        if aligned:
            self._write_staged(aligned)

    def write_through(self) -> None:
        """Hand every byte written so far to the OS, the last partial block too (zero-padded, written at its
        offset with pwrite and rewritten whole by the next write), so that a crash of the process cannot cut
        a record that was complete before this call. Leaves the file offset where the full blocks end."""
        self.flush()
        if not self._staged:
            return
        length = self._staged
        if self._direct:
            length = -(-self._staged // BLOCK) * BLOCK
            self._view[self._staged:length] = bytes(length - self._staged)
        done = 0
        while done < length:
            written = os.pwrite(self._fd, self._view[done:length], self._flushed + done)
            if written <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            done += written

    def fileno(self) -> int:
        return self._fd

    def _buffered(self) -> None:
        fcntl.fcntl(self._fd, fcntl.F_SETFL, fcntl.fcntl(self._fd, fcntl.F_GETFL) & ~os.O_DIRECT)
        self._direct = False

    def close(self, sync: bool = False) -> None:
        """Write the rest (the last block padded, then the file cut to its length); with ``sync``, fsync
        after the cut, so that a power loss cannot leave the padding behind the file's last record."""
        if self.closed:
            return
        self.closed = True
        try:
            if self._staged:
                size = self._flushed + self._staged
                padded = -(-self._staged // BLOCK) * BLOCK
                self._view[self._staged:padded] = bytes(padded - self._staged)
                self._write_staged(padded)
                os.ftruncate(self._fd, size)
            if sync:
                os.fsync(self._fd)
        finally:
            os.close(self._fd)
            self._view.release()
            self._staging.close()


def open_exclusive(path: Path, buffering: int) -> BinaryIO | DirectFile:
    """Create ``path`` (never overwriting it) for writing: direct I/O where the filesystem allows it."""
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
    return DirectFile(fd)
