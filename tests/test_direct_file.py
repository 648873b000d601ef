"""The O_DIRECT writer: same bytes as a plain file, whatever the write sizes, and a buffered fallback."""
from __future__ import annotations

import errno
import os
import random
from pathlib import Path

import pytest

from baglib import direct_file
from baglib.direct_file import BLOCK, STAGING, DirectFile, open_exclusive


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
