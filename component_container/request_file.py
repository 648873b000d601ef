"""Reading a small YAML file that a request named, without disclosing anything about it to the requester.

A path parameter (a QoS override file) may name any file the container's user can read; the caller of the
load service is anonymous, and the error it gets back is also logged. So failures say which parameter and
what kind of problem (not found, not a regular file, not readable, too large, not valid YAML) and never carry
the file's bytes, a parser message (PyYAML quotes the offending text) or anything else read from it.
"""
from __future__ import annotations

import errno
import os
import stat
from pathlib import Path
from typing import Any

import yaml

#: The largest file read: override files are a few lines; a request must not make the container read a disk.
MAX_BYTES = 1024 * 1024

_NOT_FOUND = {errno.ENOENT, errno.ENOTDIR}
_NOT_READABLE = {errno.EACCES, errno.EPERM}


def read_yaml(parameter: str, path: Path, max_bytes: int = MAX_BYTES) -> Any:
    """The YAML document in the regular file ``path``; ValueError naming ``parameter`` and the problem only."""
    def refuse(problem: str) -> ValueError:
        return ValueError(f"parameter '{parameter}': {problem}")

    try:
        # Non-blocking: opening a FIFO for reading would otherwise wait for a writer, hanging the load service.
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        if exc.errno in _NOT_FOUND:
            raise refuse("file not found") from None
        if exc.errno in _NOT_READABLE:
            raise refuse("file not readable (permission denied)") from None
        raise refuse(f"file cannot be opened ({errno.errorcode.get(exc.errno or 0, 'error')})") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise refuse("not a regular file")
        data = _read_at_most(fd, max_bytes + 1)  # more than max_bytes means too large, without reading it all
    except OSError:
        raise refuse("file not readable (read error)") from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise refuse(f"file larger than {max_bytes} bytes")
    try:
        return yaml.safe_load(data)
    except Exception:  # noqa: BLE001 - any parser failure (YAMLError, RecursionError, int digit limit) alike
        raise refuse("not valid YAML") from None


def _read_at_most(fd: int, size: int) -> bytes:
    chunks: list[bytes] = []
    while size > 0 and (chunk := os.read(fd, size)):
        chunks.append(chunk)
        size -= len(chunk)
    return b"".join(chunks)
