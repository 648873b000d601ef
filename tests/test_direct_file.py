"""The O_DIRECT writer: same bytes as a plain file, whatever the write sizes; big buffers written from where they
are when aligned; and a buffered fallback."""
from __future__ import annotations

import errno
import os
import random
from pathlib import Path

import pytest

from baglib.write import direct_file
from baglib.write.direct_file import BLOCK, IN_PLACE_MIN, STAGING, DirectFile, address, open_exclusive


@pytest.mark.parametrize("seed", range(5))
def test_content_and_length_equal_what_was_written(tmp_path: Path, seed: int) -> None:
    rng = random.Random(seed)
    path = tmp_path / "out.bin"
    file = open_exclusive(path, 4096)
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
            file.flush()  # leaves at most one partial block staged
            assert file.tell() == len(expected)
    file.close()
    file.close()  # idempotent
    assert path.read_bytes() == bytes(expected)


@pytest.mark.parametrize("seed", range(5))
def test_big_buffers_placed_by_gap_before_are_written_in_place(tmp_path: Path, seed: int) -> None:
    """A big buffer preceded by the gap the file asks for goes out from its own memory, all but its unaligned
    head and tail; one preceded by any other gap is staged; the file holds exactly what was written."""
    rng = random.Random(seed)
    print(f"seed {seed}")
    path = tmp_path / "out.bin"
    file = open_exclusive(path, 4096)
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
            rng.choice([file.flush, file.write_through])()
    assert in_place > 10 * IN_PLACE_MIN  # most of the big buffers went out in place
    file.close()
    assert path.read_bytes() == bytes(expected)


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
