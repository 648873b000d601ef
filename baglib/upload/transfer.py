"""Uploading one file, resumably, and verifying the remote copy against the local bytes.

A file of up to one part goes in a single PUT with its Content-MD5; a larger one as a multipart upload whose id
and confirmed parts the journal keeps, PARTS_IN_FLIGHT parts under way at a time (a part is confirmed in the
journal once the store answered it and every part before it). Resuming asks the server which parts it holds
(``ListParts``) and reuses each whose ETag is the MD5 of the local part, so a cut costs at most the parts in
flight. Every part carries its Content-MD5 and the ETag the server answers must be that MD5. After completion the
object's size and ETag must match what the local bytes give (:mod:`~baglib.upload.digests`) before the file
counts as verified; a mismatch is counted and the file uploaded again, never deleted.

An object already at the key is never overwritten blindly: if it verifies against the local file, nothing is
transferred (uploading a bag twice costs a read of it, no bytes); if it holds something else, the upload stops
with an error naming the key (another robot's bag under the same name, say), unless this journal's own earlier
attempt put it there.
"""
from __future__ import annotations

import base64
import collections
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import botocore.exceptions

from baglib.upload.client import UploadError, is_not_found
from baglib.upload.digests import PART_SIZE_KEY, Digests, matches_object, part_size_for, parts_of
from baglib.upload.journal import Entry, UploadJournal
from baglib.upload.throttle import Throttle


#: Parts of a multipart upload sent at once (each on a connection of its own): while the store takes one part in,
#: the next is read, hashed and sent, so the client's CPU time (MD5, SigV4's SHA-256 of the payload) and the
#: store's overlap instead of taking turns. The memory the upload holds is at most this many parts.
PARTS_IN_FLIGHT = 4


class Interrupted(Exception):
    """The uploader was asked to stop between two requests."""


@dataclass(frozen=True)
class _PartSent:
    """A part whose request is under way."""

    number: int
    md5: str
    length: int
    request: Future[dict[str, Any]]


@dataclass
class Transferred:
    """What uploading one file took: bytes sent, bytes the server already had, and whether the object was
    already there whole (nothing sent)."""

    sent: int = 0
    reused: int = 0
    already_there: bool = False


def _md5_header(hex_digest: str) -> str:
    return base64.b64encode(bytes.fromhex(hex_digest)).decode()


def _etag(value: str) -> str:
    return value.strip('"')


class FileUpload:
    """Uploads one journal entry with ``client``; ``progress(bytes)`` is called after each request."""

    def __init__(self, client: Any, journal: UploadJournal, entry: Entry, throttle: Throttle,
                 progress: Callable[[int], None] = lambda sent: None) -> None:
        """``throttle`` also carries the stop: a request not yet started is not started once it is set."""
        self.client = client
        self.journal = journal
        self.entry = entry
        self.throttle = throttle
        self.progress = progress
        self.target = f"s3://{entry.bucket}/{entry.key}"

    def run(self) -> Transferred:
        """Upload and verify; raises FileNotFoundError (the local file is gone), UploadError or Interrupted."""
        entry = self.entry
        size = entry.local.stat().st_size
        if entry.upload_id is None and not entry.mismatches:
            existing = self._head()
            if existing is not None:
                return self._existing(existing)
        part_size = entry.part_size or part_size_for(size)
        if size <= part_size:
            return self._single(size, part_size)
        return self._multipart(size, part_size)

    # --- the object at the key --------------------------------------------------------------------------
    def _head(self) -> dict[str, Any] | None:
        """The object at the key (HeadObject's answer), None if there is none. Asked with a listing first: a
        HEAD answer has no body, so its errors come without a code (a missing bucket, refused credentials)."""
        listing = self.client.list_objects_v2(Bucket=self.entry.bucket, Prefix=self.entry.key, MaxKeys=1)
        if not any(item["Key"] == self.entry.key for item in listing.get("Contents", [])):
            return None
        try:
            return self.client.head_object(Bucket=self.entry.bucket, Key=self.entry.key)
        except botocore.exceptions.ClientError as error:
            if is_not_found(error):
                return None
            raise

    def _existing(self, head: dict[str, Any]) -> Transferred:
        """An object is at the key already: done if it is this file, an error otherwise."""
        if matches_object(self.entry.local, head):
            return Transferred(already_there=True)
        raise UploadError(f"{self.target} exists and holds other content ({head['ContentLength']} bytes, "
                          f"ETag {head['ETag']}) than {self.entry.local}: not overwritten", permanent=True)

    def _verify(self, size: int, digests: Digests, multipart: bool) -> None:
        head = self._head()
        if head is None or head["ContentLength"] != size or \
                not digests.matches(_etag(head["ETag"]), multipart, self.entry.local):
            found = "nothing" if head is None else f"{head['ContentLength']} bytes, ETag {head['ETag']}"
            error = (f"{self.target} did not verify: the store holds {found}, the local file {size} bytes, "
                     f"ETag {digests.etag(multipart)}; uploading it again")
            self.journal.mismatch(self.entry.id, error)
            raise UploadError(error)

    # --- one request ------------------------------------------------------------------------------------
    def _single(self, size: int, part_size: int) -> Transferred:
        data = self.entry.local.read_bytes()
        if len(data) != size:
            raise UploadError(f"{self.entry.local} changed size while being uploaded")
        digests = Digests()
        md5 = digests.add(data)
        if not self.throttle.wait(size):
            raise Interrupted()
        answer = self.client.put_object(Bucket=self.entry.bucket, Key=self.entry.key, Body=data,
                                        ContentMD5=_md5_header(md5), Metadata={PART_SIZE_KEY: str(part_size)})
        self.journal.count_sent(self.entry.id, size, 0)
        self.progress(size)
        if _etag(answer["ETag"]) != md5:
            self.journal.mismatch(self.entry.id, f"{self.target}: the store answered ETag {answer['ETag']} for "
                                                 f"content whose MD5 is {md5}")
            raise UploadError(f"{self.target}: the store received other bytes than were sent (ETag mismatch)")
        self._verify(size, digests, multipart=False)
        return Transferred(sent=size)

    # --- multipart --------------------------------------------------------------------------------------
    def _server_parts(self, upload_id: str) -> dict[int, tuple[str, int]] | None:
        """The parts the server holds for ``upload_id`` (None: it knows no such upload any more)."""
        parts: dict[int, tuple[str, int]] = {}
        marker = 0
        try:
            while True:
                page = self.client.list_parts(Bucket=self.entry.bucket, Key=self.entry.key, UploadId=upload_id,
                                              PartNumberMarker=marker)
                for part in page.get("Parts", []):
                    parts[part["PartNumber"]] = (_etag(part["ETag"]), part["Size"])
                if not page.get("IsTruncated"):
                    return parts
                marker = page["NextPartNumberMarker"]
        except botocore.exceptions.ClientError as error:
            if is_not_found(error):
                return None
            raise

    def _confirm(self, part: _PartSent) -> int:
        """Wait for ``part``'s request; check the ETag the store answered and confirm it in the journal; the
        bytes sent."""
        answer = part.request.result()
        if _etag(answer["ETag"]) != part.md5:
            raise UploadError(f"{self.target}: the store answered ETag {answer['ETag']} for part {part.number}, "
                              f"whose MD5 is {part.md5}: sending it again")
        self.journal.confirm_part(self.entry.id, part.number, part.md5, part.length)
        self.progress(part.length)
        return part.length

    def _multipart(self, size: int, part_size: int) -> Transferred:
        entry = self.entry
        upload_id, held = entry.upload_id, None
        if upload_id is not None:
            held = self._server_parts(upload_id)
            if held is None:  # completed (then killed before it was verified) or aborted: look at the key
                self.journal.start_multipart(entry.id, None, None)
                existing = self._head()
                if existing is not None and not entry.mismatches:
                    return self._existing(existing)
                upload_id = None
        if upload_id is None:
            upload_id = self.client.create_multipart_upload(
                Bucket=entry.bucket, Key=entry.key, Metadata={PART_SIZE_KEY: str(part_size)})["UploadId"]
            self.journal.start_multipart(entry.id, upload_id, part_size)
            held = {}
        done = Transferred()
        digests = Digests()
        completed: list[dict[str, Any]] = []
        in_flight: collections.deque[_PartSent] = collections.deque()
        with open(entry.local, "rb") as stream, ThreadPoolExecutor(PARTS_IN_FLIGHT, "upload_part") as senders:
            for number, offset, length in parts_of(size, part_size):
                data = stream.read(length)
                if len(data) != length:
                    raise UploadError(f"{entry.local} changed size while being uploaded")
                md5 = digests.add(data)
                if held.get(number) == (md5, length):
                    done.reused += length
                else:
                    if not self.throttle.wait(length):
                        raise Interrupted()
                    in_flight.append(_PartSent(number, md5, length, senders.submit(
                        self.client.upload_part, Bucket=entry.bucket, Key=entry.key, UploadId=upload_id,
                        PartNumber=number, Body=data, ContentMD5=_md5_header(md5))))
                    del data  # the request holds the part until it is sent: PARTS_IN_FLIGHT parts at most
                    if len(in_flight) == PARTS_IN_FLIGHT:
                        done.sent += self._confirm(in_flight.popleft())
                completed.append({"PartNumber": number, "ETag": f'"{md5}"'})
            while in_flight:
                done.sent += self._confirm(in_flight.popleft())
        self.journal.count_sent(entry.id, 0, done.reused)
        self.client.complete_multipart_upload(Bucket=entry.bucket, Key=entry.key, UploadId=upload_id,
                                              MultipartUpload={"Parts": completed})
        self._verify(size, digests, multipart=True)
        return done
