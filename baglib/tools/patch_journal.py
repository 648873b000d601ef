"""Patching a storage file in place, crash-safe: a small journal of the patch is made durable first.

``bag recover`` repairs a file a crash left unfinished by cutting it at the first damage and appending what
belongs after the kept part (an MCAP file's rebuilt indexes, summary and footer). Doing that in place needs
no free space beyond the journal and the growth of the file, which is what a recorder killed on a nearly full
disk leaves. The journal ``.<file>.recover-journal`` holds the cut offset, the new tail and the original bytes
the tail overwrites, with a CRC over all of it, and is fsynced (and its name with the directory) before the file
is touched, so after any interruption:

* no valid journal: the file was never touched (a half-written journal is discarded);
* a valid journal: the patch may be partly applied; the next run applies it again (it is idempotent: the same
  bytes at the same offset, the same length) and then removes the journal.

A patch that fails while it is applied (no space for the growth of the file) is undone at once from the saved
bytes, so that a failed repair leaves the file as it found it.
"""
from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

from baglib.format.durable import fsync_directory

__all__ = ["JOURNAL_SUFFIX", "Patch", "apply_all", "finish_journals"]

JOURNAL_SUFFIX = ".recover-journal"
_MAGIC = b"IPCRECJ1"
_HEAD = struct.Struct("<QQQQ")  # original size, cut offset, tail length, saved length


@dataclass(frozen=True)
class Patch:
    """Cut ``path`` at ``cut`` and write ``tail`` there; ``saved`` holds the original bytes the tail covers and
    ``original_size`` the file's size before, to undo it."""

    path: Path
    original_size: int
    cut: int
    tail: bytes
    saved: bytes

    @classmethod
    def prepare(cls, path: Path, cut: int, tail: bytes) -> Patch:
        size = path.stat().st_size
        with open(path, "rb") as file:
            file.seek(cut)
            saved = file.read(max(0, min(size, cut + len(tail)) - cut))
        return cls(path, size, cut, tail, saved)

    @property
    def journal(self) -> Path:
        return _journal_of(self.path)

    def encode(self) -> bytes:
        body = _MAGIC + _HEAD.pack(self.original_size, self.cut, len(self.tail), len(self.saved)) \
            + self.tail + self.saved
        return body + struct.pack("<I", zlib.crc32(body))

    @classmethod
    def decode(cls, path: Path, data: bytes) -> Patch | None:
        """The patch a journal holds, or None if the journal is incomplete or damaged."""
        if len(data) < len(_MAGIC) + _HEAD.size + 4 or not data.startswith(_MAGIC):
            return None
        body, (crc,) = data[:-4], struct.unpack("<I", data[-4:])
        if zlib.crc32(body) != crc:
            return None
        original_size, cut, tail_length, saved_length = _HEAD.unpack_from(body, len(_MAGIC))
        start = len(_MAGIC) + _HEAD.size
        if start + tail_length + saved_length != len(body):
            return None
        return cls(path, original_size, cut, body[start:start + tail_length],
                   body[start + tail_length:start + tail_length + saved_length])

    def write_journal(self) -> None:
        temporary = self.journal.with_name(self.journal.name + ".tmp")
        try:
            with open(temporary, "wb") as file:
                file.write(self.encode())
                file.flush()
                os.fsync(file.fileno())
            os.rename(temporary, self.journal)
        except BaseException:
            temporary.unlink(missing_ok=True)
            raise
        fsync_directory(self.path.parent)

    def write_tail(self) -> None:
        """Write the tail at the cut (durable when this returns); the only step that may need new space."""
        _write(self.path, self.cut, self.tail, None)

    def end_after_tail(self) -> None:
        """End the file after the tail (frees space, never needs any)."""
        _write(self.path, self.cut, b"", self.cut + len(self.tail))

    def apply(self) -> None:
        self.write_tail()
        self.end_after_tail()

    def undo(self) -> None:
        """Put the saved bytes back and the size as it was. Run before :meth:`end_after_tail`, it needs no new
        space and leaves every byte of the file as it was."""
        _write(self.path, self.cut, self.saved, self.original_size)

    def forget(self) -> None:
        self.journal.unlink(missing_ok=True)
        fsync_directory(self.path.parent)


def apply_all(patches: list[Patch]) -> None:
    """Journal every patch, write every tail, then end every file after its tail. If a journal or a tail cannot
    be written (no space), every patch is undone and its journal removed: the files are as they were found."""
    journaled: list[Patch] = []
    try:
        for patch in patches:
            patch.write_journal()
            journaled.append(patch)
        for patch in patches:
            patch.write_tail()
    except BaseException:
        for patch in journaled:
            patch.undo()
            patch.forget()
        raise
    for patch in patches:
        patch.end_after_tail()
    for patch in patches:
        patch.forget()


def finish_journals(directory: Path) -> list[str]:
    """Apply again what an interrupted run journaled in ``directory``, discard incomplete journals; returns
    the names of the files patched."""
    finished = []
    for leftover in directory.glob(f".*{JOURNAL_SUFFIX}.tmp"):
        leftover.unlink()
    for journal in sorted(directory.glob(f".*{JOURNAL_SUFFIX}")):
        target = directory / journal.name[1:-len(JOURNAL_SUFFIX)]
        patch = Patch.decode(target, journal.read_bytes()) if target.is_file() else None
        if patch is not None:
            patch.apply()
            finished.append(target.name)
        journal.unlink()
    if finished:
        fsync_directory(directory)
    return finished


def _journal_of(path: Path) -> Path:
    return path.with_name(f".{path.name}{JOURNAL_SUFFIX}")


def _write(path: Path, offset: int, data: bytes, size: int | None) -> None:
    """``data`` at ``offset``, then the file's size set to ``size`` (unless None), fsynced."""
    descriptor = os.open(path, os.O_WRONLY)
    try:
        view = memoryview(data)
        while view:
            written = os.pwrite(descriptor, view, offset)
            view, offset = view[written:], offset + written
        if size is not None:
            os.ftruncate(descriptor, size)
        os.fsync(descriptor)
    finally:
        os.close(descriptor)
