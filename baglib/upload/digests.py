"""What a store's ETag of a file is, computed from the local bytes, so a remote copy can be verified.

An S3 ETag is the MD5 of the content for a single PUT, and for a multipart object the MD5 of the concatenated
binary MD5s of its parts followed by ``-N``: not a hash of the whole file, so the local side computes the same
thing with the same part size, from the MD5 each part's Content-MD5 needs anyway. Some stores (localbucket among
them) give a completed multipart object the MD5 of the whole content instead; that one is computed, by reading
the file once more, only when a store answers such an ETag. The part size is stored with the object
(user metadata ``part-size``), so a later check or a download can compute it too.
"""
from __future__ import annotations

import hashlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

MiB = 1 << 20
#: The part size of a multipart upload (S3's minimum is 5 MiB for all but the last part); doubled for a file that
#: would need more than MAX_PARTS parts. Files up to one part are uploaded with a single PUT.
PART_SIZE = 8 * MiB
MAX_PARTS = 10_000
#: The user metadata key (``x-amz-meta-part-size``) that records the part size.
PART_SIZE_KEY = "part-size"


def part_size_for(size: int, part_size: int = PART_SIZE) -> int:
    """The part size for a file of ``size`` bytes: ``part_size``, doubled until the parts fit S3's limit."""
    while -(-size // part_size) > MAX_PARTS:
        part_size *= 2
    return part_size


def parts_of(size: int, part_size: int) -> Iterator[tuple[int, int, int]]:
    """(part number from 1, offset, length) of each part of a file of ``size`` bytes."""
    for number, offset in enumerate(range(0, size, part_size), start=1):
        yield number, offset, min(part_size, size - offset)


@dataclass
class Digests:
    """The MD5 of each part, filled as the parts are read in order: one hash of the bytes, the one the parts'
    Content-MD5 needs anyway."""

    part_md5s: list[bytes] = field(default_factory=list)

    def add(self, data: bytes | memoryview) -> str:
        """Add the next part; its MD5 in hex (an ETag without quotes)."""
        digest = hashlib.md5(data)
        self.part_md5s.append(digest.digest())
        return digest.hexdigest()

    def etag(self, multipart: bool) -> str:
        """The ETag (without quotes) S3 gives the content: its MD5 for a single PUT; for a multipart upload the
        MD5 of the parts' binary MD5s, then ``-`` and the number of parts."""
        if not multipart:
            return self.part_md5s[0].hex() if self.part_md5s else hashlib.md5().hexdigest()
        return f"{hashlib.md5(b''.join(self.part_md5s)).hexdigest()}-{len(self.part_md5s)}"

    def matches(self, etag: str, multipart: bool, path: Path) -> bool:
        """Whether a store's ``etag`` (without quotes) is what the local file at ``path`` gives: :meth:`etag`, or
        for a multipart object the MD5 of the whole content, which some stores give instead. That one is computed
        only for such an ETag (no ``-N``), reading the file again: hashing every upload twice would cost all
        stores the CPU time that one needs."""
        if etag == self.etag(multipart):
            return True
        if not multipart or "-" in etag:
            return False
        with open(path, "rb") as stream:
            return etag == hashlib.file_digest(stream, "md5").hexdigest()


def file_digests(path: Path, part_size: int, chunk: int = PART_SIZE) -> Digests:
    """The digests of the file at ``path`` for parts of ``part_size`` bytes, read ``chunk`` bytes at a time."""
    digests = Digests()
    with open(path, "rb") as stream:
        while True:
            part = hashlib.md5()
            left = part_size
            while left:
                data = stream.read(min(chunk, left))
                if not data:
                    break
                part.update(data)
                left -= len(data)
            if left == part_size:
                return digests
            digests.part_md5s.append(part.digest())
            if left:
                return digests


def matches_object(path: Path, head: Mapping[str, Any]) -> bool:
    """Whether the local file at ``path`` holds the object a HeadObject answer ``head`` describes: the same size,
    and an ETag its bytes give with the part size the object records (the default one if it records none)."""
    size = int(head["ContentLength"])
    if path.stat().st_size != size:
        return False
    part_size = int(head.get("Metadata", {}).get(PART_SIZE_KEY) or 0) or part_size_for(size)
    return file_digests(path, part_size).matches(str(head["ETag"]).strip('"'), size > part_size, path)
