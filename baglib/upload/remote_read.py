"""Reading a bag where it was uploaded: the objects under its prefix, its ``metadata.yaml``, and one object as a
seekable file read with ranged GETs.

``bag info`` of an ``s3://`` bag needs ``metadata.yaml`` and the sizes of the files (one listing), never the
files themselves. A single MCAP object is read the way the local reader reads a file: the footer and the summary
section at its end, and the records the summary points to. :class:`RangedFile` gives the reader exactly those
bytes, each window fetched with one ranged GET (``If-Match`` the ETag it opened, so an object replaced meanwhile
is an error, never a mix of two), and counts what it fetched: for a bag of megabytes, info costs a few windows.
"""
from __future__ import annotations

import io
import threading
from typing import Any

import botocore.exceptions

from baglib.format.metadata import METADATA_FILENAME
from baglib.read.metadata_read import StoredMetadata, metadata_from_text
from baglib.read.storage_reader import BagReadError
from baglib.upload.client import UploadError, is_not_found
from baglib.upload.location import S3Location

#: Bytes fetched at least per GET: a summary section of a small bag, with its footer, in one request.
WINDOW = 64 * 1024
#: Windows kept: the file's start (its magic), its end (footer and summary) and the records in between.
WINDOWS_KEPT = 4


def object_sizes(client: Any, location: S3Location) -> dict[str, int]:
    """The objects under ``location`` (a bag's prefix) as name (the key below the prefix) -> size."""
    prefix = f"{location.prefix}/" if location.prefix else ""
    sizes: dict[str, int] = {}
    for page in client.get_paginator("list_objects_v2").paginate(Bucket=location.bucket, Prefix=prefix):
        for item in page.get("Contents", []):
            name = item["Key"][len(prefix):]
            if name and not name.endswith("/"):
                sizes[name] = int(item["Size"])
    return sizes


def read_metadata(client: Any, location: S3Location) -> StoredMetadata:
    """The ``metadata.yaml`` of the bag at ``location``; UploadError when the store has none (the bag is not
    complete there), BagReadError when it is not a bag's metadata."""
    key = location.key(METADATA_FILENAME)
    try:
        text = client.get_object(Bucket=location.bucket, Key=key)["Body"].read().decode("utf-8")
    except botocore.exceptions.ClientError as error:
        if is_not_found(error):
            raise UploadError(f"{location.uri} is not a complete bag in the store: it has no {METADATA_FILENAME} "
                              "(an upload still under way or cut short, or no bag there)", permanent=True) from None
        raise
    except UnicodeDecodeError as error:
        raise BagReadError(f"s3://{location.bucket}/{key}: not UTF-8 text ({error.reason})") from None
    return metadata_from_text(text, f"s3://{location.bucket}/{key}")


class RangedFile(io.BufferedIOBase):
    """The object ``key`` of ``bucket`` as a read-only, seekable binary file, read with ranged GETs.

    ``pread`` reads at an offset without moving the position, as ``os.pread`` does (thread-safe), so the bag
    reader can take it for a file descriptor. Reads are served from up to :data:`WINDOWS_KEPT` windows of at
    least :data:`WINDOW` bytes; a window near the end of the object reaches back from it, so reading the footer
    fetches the summary before it too. ``fetched`` and ``requests`` count what was transferred. Buffered already,
    so no reader wraps it in a BufferedReader of its own (the mcap library wraps a raw stream, and closes it
    with that wrapper).
    """

    def __init__(self, client: Any, bucket: str, key: str) -> None:
        super().__init__()
        self.client, self.bucket, self.key = client, bucket, key
        head = client.head_object(Bucket=bucket, Key=key)
        self.size = int(head["ContentLength"])
        self.etag = str(head["ETag"])
        self.fetched = 0
        self.requests = 0
        self._position = 0
        self._windows: list[tuple[int, bytes]] = []
        self._lock = threading.Lock()

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._position

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._position, io.SEEK_END: self.size}[whence]
        if base + offset < 0:
            raise ValueError(f"negative seek position {base + offset}")
        self._position = base + offset
        return self._position

    def read(self, size: int | None = -1) -> bytes:
        data = self.pread(self.size - self._position if size is None or size < 0 else size, self._position)
        self._position += len(data)
        return data

    def readinto(self, buffer: Any) -> int:
        data = self.read(len(buffer))
        buffer[:len(data)] = data
        return len(data)

    def pread(self, length: int, offset: int) -> bytes:
        """Up to ``length`` bytes from ``offset`` (fewer only at the end of the object)."""
        end = min(self.size, offset + length)
        if offset >= end:
            return b""
        with self._lock:
            for start, data in self._windows:
                if start <= offset and end <= start + len(data):
                    return data[offset - start:end - start]
            start = max(0, min(offset, self.size - WINDOW)) if end - offset < WINDOW else offset
            data = self._get(start, max(end, min(self.size, start + WINDOW)))
            self._windows = [(start, data), *self._windows[:WINDOWS_KEPT - 1]]
        return data[offset - start:end - start]

    def _get(self, start: int, end: int) -> bytes:
        answer = self.client.get_object(Bucket=self.bucket, Key=self.key, IfMatch=self.etag,
                                        Range=f"bytes={start}-{end - 1}")
        data = answer["Body"].read()
        if len(data) != end - start:
            raise UploadError(f"s3://{self.bucket}/{self.key}: asked for bytes {start}-{end - 1}, received "
                              f"{len(data)} bytes")
        self.requests += 1
        self.fetched += len(data)
        return data
