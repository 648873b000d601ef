"""The O_DIRECT writer: same bytes as a plain file, whatever the write sizes; big buffers written from where they
are when aligned; and a buffered fallback."""
from __future__ import annotations

import errno
import mmap
import os
import random
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from baglib.write import direct_file
from baglib.write.direct_file import BLOCK, GATHER, IN_PLACE_MIN, STAGING, DirectFile, address, open_exclusive

#: Gathering off, a little (a few blocks: the queue is written often, mid-buffer), and the recorder's.
GATHERS = [0, 3 * BLOCK + 1, GATHER]


@pytest.mark.parametrize("gather", GATHERS)
@pytest.mark.parametrize("seed", range(5))
def test_content_and_length_equal_what_was_written(tmp_path: Path, seed: int, gather: int) -> None:
    rng = random.Random(seed)
    path = tmp_path / "out.bin"
    file = open_exclusive(path, 4096, gather)
    assert isinstance(file, DirectFile)  # the test filesystem supports O_DIRECT; else this tests nothing
    expected = bytearray()
    for _ in range(40):
        size = rng.choice([0, 1, 7, BLOCK - 1, BLOCK, BLOCK + 3, STAGING - 5, STAGING + 11, 3 * STAGING + 1])
        piece = rng.randbytes(size)
        kind = rng.choice([bytes, bytearray, memoryview])
        assert file.write(kind(piece)) == size
        expected += piece
        assert file.tell() == len(expected)
        if rng.random() < 0.3:
            rng.choice([file.flush, file.write_gathered])()  # leave at most one partial block staged
            assert file.tell() == len(expected)
    file.close()
    file.close()  # idempotent
    assert path.read_bytes() == bytes(expected)


@pytest.mark.parametrize("gather", GATHERS)
@pytest.mark.parametrize("seed", range(5))
def test_big_buffers_placed_by_gap_before_are_written_in_place(tmp_path: Path, seed: int, gather: int) -> None:
    """A big buffer preceded by the gap the file asks for goes out from its own memory, all but its unaligned
    head and tail; one preceded by any other gap is staged; the file holds exactly what was written."""
    rng = random.Random(seed)
    print(f"seed {seed}")
    path = tmp_path / "out.bin"
    file = open_exclusive(path, 4096, gather)
    assert isinstance(file, DirectFile)
    backing = bytearray(rng.randbytes(2 * IN_PLACE_MIN + 2 * BLOCK))
    expected = bytearray()
    in_place = 0
    for _ in range(30):
        before = rng.randbytes(rng.choice([0, 1, 9, BLOCK + 5, IN_PLACE_MIN - 1]))
        start, size = rng.randrange(2 * BLOCK), rng.randrange(IN_PLACE_MIN, 2 * IN_PLACE_MIN)
        big = rng.choice([memoryview, bytes])(memoryview(backing)[start:start + size])  # writable or read-only
        gap = file.gap_before(big, len(before))
        assert gap is not None and 0 <= gap < BLOCK
        aligned = rng.random() < 0.7
        for piece in (rng.randbytes(gap if aligned else gap + rng.randrange(1, BLOCK)), before, big):
            assert file.write(piece) == len(piece)
            expected += piece
        if aligned:
            in_place += (size - (-address(memoryview(big)) % BLOCK)) // BLOCK * BLOCK
        assert file.in_place == in_place and file.tell() == len(expected)
        if rng.random() < 0.3:
            rng.choice([file.flush, file.write_gathered, file.write_through])()
    assert in_place > 10 * IN_PLACE_MIN  # most of the big buffers went out in place
    file.close()
    assert path.read_bytes() == bytes(expected)


def aligned_frame(size: int) -> memoryview:
    """A page-aligned buffer of ``size`` random bytes (as a camera frame that lands on a block boundary)."""
    backing = mmap.mmap(-1, size)
    backing.write(os.urandom(size))
    return memoryview(backing)


def test_gathered_writes_wait_for_gather_bytes_or_the_writer(tmp_path: Path, monkeypatch) -> None:
    """With gathering, whole blocks go to the disk in one pwritev once ``gather`` bytes are queued, or when the
    writer asks, on an I/O thread; big buffers are referenced until then (not copied); write_through() returns once
    every write has; and the file ends up byte for byte."""
    calls: list[int] = []
    real_pwritev = os.pwritev
    monkeypatch.setattr(direct_file.os, "pwritev", lambda fd, buffers, offset: calls.append(len(buffers))
                        or real_pwritev(fd, buffers, offset))
    path = tmp_path / "out.bin"
    file = open_exclusive(path, 4096, 4 * IN_PLACE_MIN)
    assert isinstance(file, DirectFile)
    frames = [aligned_frame(IN_PLACE_MIN) for _ in range(6)]
    for frame in frames[:3]:
        file.write(frame)
    assert os.path.getsize(path) == 0 and not calls  # 3 of the 4 frames a gather holds: nothing written yet
    file.write(frames[3])
    file.write_through()  # nothing staged: only waits for the gathered write
    assert os.path.getsize(path) == 4 * IN_PLACE_MIN and calls == [4]  # one write for all four
    file.write(frames[4])
    file.write(b"tail")
    file.write_gathered()  # the writer has nothing more at hand: the whole blocks go now, the partial one stays
    file.write_through()  # and now the partial block too, padded
    assert os.path.getsize(path) == 5 * IN_PLACE_MIN + BLOCK and calls == [4, 1, 1]
    file.write(frames[5])
    file.close()
    assert path.read_bytes() == b"".join(bytes(frame) for frame in frames[:5]) + b"tail" + bytes(frames[5])
    assert file.in_place >= 5 * IN_PLACE_MIN


def test_without_gathering_a_big_buffer_is_written_before_write_returns(tmp_path: Path) -> None:
    """The library default: a caller may reuse its buffer as soon as write() returns."""
    path = tmp_path / "out.bin"
    file = open_exclusive(path, 4096)
    frame = aligned_frame(IN_PLACE_MIN)
    expected = bytes(frame)
    file.write(frame)
    assert os.path.getsize(path) == IN_PLACE_MIN and file.in_place == IN_PLACE_MIN
    frame[:] = bytes(IN_PLACE_MIN)  # reused by the caller
    file.close()
    assert path.read_bytes() == expected


@pytest.mark.parametrize("gather", GATHERS)
def test_after_a_failed_write_the_file_takes_nothing_more(tmp_path: Path, gather: int) -> None:
    """A write that fails (the file size limit, as a full disk), on the writing thread or an I/O thread, is
    raised by a later call, and leaves the file as the successful writes made it: close() adds nothing (no
    padding, no later bytes at the failed offset), further writes raise."""
    limit = 2 * IN_PLACE_MIN + 3 * BLOCK
    path = tmp_path / "out.bin"
    script = (f"import resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
              f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))")
    # RLIMIT_FSIZE applies to the whole process: a child does the writing.
    child = subprocess.run([sys.executable, "-c", script + f"""
import os, mmap
from baglib.write.direct_file import open_exclusive
file = open_exclusive(__import__('pathlib').Path({str(path)!r}), 4096, {gather})
frames = []
for n in range(4):
    m = mmap.mmap(-1, {IN_PLACE_MIN}); m.write(bytes([n + 1]) * {IN_PLACE_MIN}); frames.append(memoryview(m))
try:
    for frame in frames:
        file.write(frame)
        file.write(b"x" * 5)
    file.write_through()  # a gathered write fails on an I/O thread: its error comes here at the latest
except OSError as error:
    print("failed", error.errno)
    try:
        file.write(b"more")
    except OSError as again:
        print("again", again.errno)
file.close()
"""], capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1])
    assert child.returncode == 0, child.stderr
    assert child.stdout.split() == ["failed", str(errno.EFBIG), "again", str(errno.EIO)], child.stdout
    data = path.read_bytes()
    assert len(data) <= limit and len(data) % BLOCK == 0  # no padded tail, no truncate after the failure
    expected = b"".join(bytes([n + 1]) * IN_PLACE_MIN + b"x" * 5 for n in range(4))
    assert data == expected[:len(data)] and len(data) >= 2 * IN_PLACE_MIN


def test_close_after_a_failed_write_waits_for_the_writes_still_running(tmp_path: Path, monkeypatch) -> None:
    """A gathered write fails while the next one still runs on the other I/O thread: the failure is raised by the
    next call, and close() waits for the running write before it closes the descriptor (which the process could
    otherwise hand to another file, and the late write would land there)."""
    seen: dict[str, Any] = {}
    real_pwritev = os.pwritev
    calls = iter(range(2))

    def slow_pwritev(fd: int, buffers: Any, offset: int) -> int:
        if next(calls, None) == 0:
            time.sleep(0.2)
            raise OSError(errno.ENOSPC, "No space left on device")
        time.sleep(0.8)
        seen["fd_open"] = os.fstat(fd) is not None
        seen["written"] = real_pwritev(fd, buffers, offset)
        return seen["written"]

    monkeypatch.setattr(direct_file.os, "pwritev", slow_pwritev)
    file = open_exclusive(tmp_path / "out.bin", 4096, IN_PLACE_MIN)
    assert isinstance(file, DirectFile)
    frames = [aligned_frame(IN_PLACE_MIN) for _ in range(3)]
    file.write(frames[0])  # the first gathered write: fails after 0.2 s
    file.write(frames[1])  # the second, on the other thread: still running when the first has failed
    time.sleep(0.4)
    with pytest.raises(OSError) as failure:
        file.write(frames[2])
    assert failure.value.errno == errno.ENOSPC and "written" not in seen
    file.close()
    assert seen == {"fd_open": True, "written": IN_PLACE_MIN}


def test_small_buffers_and_buffered_files_never_ask_for_a_gap(tmp_path: Path) -> None:
    file = open_exclusive(tmp_path / "out.bin", 4096)
    assert isinstance(file, DirectFile)
    assert file.gap_before(bytes(IN_PLACE_MIN - 1), 0) is None
    assert file.gap_before(bytes(IN_PLACE_MIN), 0) is not None
    file._buffered()  # what a write does after the kernel refused an unaligned direct write
    assert file.gap_before(bytes(IN_PLACE_MIN), 0) is None
    file.close()


def test_existing_file_is_never_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "taken"
    path.write_bytes(b"keep")
    with pytest.raises(FileExistsError):
        open_exclusive(path, 4096)
    assert path.read_bytes() == b"keep"


def test_filesystems_without_o_direct_get_a_buffered_file(tmp_path: Path, monkeypatch) -> None:
    real_open = os.open

    def refuse_direct(path, flags, mode=0o777):  # what Linux does on such a filesystem: create, then EINVAL
        if flags & os.O_DIRECT:
            os.close(real_open(path, flags & ~os.O_DIRECT, mode))
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_open(path, flags, mode)

    monkeypatch.setattr(direct_file.os, "open", refuse_direct)
    path = tmp_path / "plain.bin"
    file = open_exclusive(path, 4096)
    assert not isinstance(file, DirectFile)
    file.write(b"abc")
    file.close()
    assert path.read_bytes() == b"abc"
