"""``bag upload``: finalized bags, or what a journal holds unfinished, uploaded in the foreground.

The same journal and uploader as the recorder's upload process, so a ``bag upload`` cut short, or a container
that exited with uploads pending, is resumed from the last confirmed part (``resume``), and a bag that is
already in the store costs a read of the local files and no transfer. Before anything is queued the bucket is
listed, so wrong credentials, a missing bucket or an unreachable endpoint are an error
that leaves every local file as it was.
"""
from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from baglib.format.bag_files import RECOVER_COMMAND, unfinished_files
from baglib.format.metadata import METADATA_FILENAME
from baglib.read.metadata_read import load_metadata
from baglib.upload.client import UploadError, describe, make_client
from baglib.upload.journal import JOURNAL_NAME, Entry, UploadJournal
from baglib.upload.location import S3Location
from baglib.upload.transfer import Transferred
from baglib.upload.uploader import Uploader
from baglib.upload.worker import lock_journal

#: Attempts at a file whose failure may pass (a server restart, a cut link) before ``bag upload`` gives up,
#: and the first back-off between them (doubled each time).
ATTEMPTS = 6
FIRST_RETRY = 1.0


@dataclass
class UploadReport:
    """What ``bag upload`` did: files verified (sent now, or already in the store), bytes sent and reused."""

    uploaded: list[str] = field(default_factory=list)
    already_there: list[str] = field(default_factory=list)
    sent: int = 0
    reused: int = 0

    def text(self) -> str:
        lines = [f"Uploaded {len(self.uploaded)} files: {self.sent} bytes sent"
                 + (f", {self.reused} bytes already sent by an earlier attempt" if self.reused else "")]
        if self.already_there:
            lines.append(f"{len(self.already_there)} files already in the store, verified: nothing transferred")
        return "\n".join(lines)


def bag_files(bag: Path) -> list[Path]:
    """A finalized bag's files, ``metadata.yaml`` last; UploadError for anything else."""
    if not (bag / METADATA_FILENAME).is_file():
        raise UploadError(f"{bag} is not a bag directory with a {METADATA_FILENAME}")
    unfinished = unfinished_files(bag)
    if unfinished:
        raise UploadError(f"{bag} is unfinished ({', '.join(unfinished)}): run '{RECOVER_COMMAND} {bag}' first")
    listed = [bag / name for name in load_metadata(bag).relative_file_paths]
    missing = [path.name for path in listed if not path.is_file()]
    if missing:
        raise UploadError(f"{bag}: {', '.join(missing)} listed in {METADATA_FILENAME} but not here")
    return [*listed, bag / METADATA_FILENAME]


def check_access(location: S3Location, endpoint_url: str) -> None:
    """UploadError, worded, unless the bucket can be reached with the configured credentials."""
    try:  # a listing, not HeadBucket: a HEAD answer has no body, so its errors come without a code
        make_client(endpoint_url).list_objects_v2(Bucket=location.bucket, Prefix=location.prefix, MaxKeys=1)
    except Exception as error:  # noqa: BLE001 - worded by describe
        raise describe(error, f"reaching {location.uri}") from None


def upload_bags(paths: Sequence[Path], location: S3Location, endpoint_url: str = "", delete_after: bool = False,
                resume: bool = False, max_rate: float = 0.0,
                progress: Callable[[Entry, int], None] = lambda entry, sent: None,
                waiting: Callable[[Path], None] = lambda journal: None) -> UploadReport:
    """Upload the bags ``paths`` under ``location`` (``PREFIX/<bag>/<file>``); with ``resume`` also every
    unfinished upload in their journals (a path may then be a directory of bags holding a journal).
    ``waiting(journal)`` is called when another process is uploading from a journal (this one waits for it)."""
    check_access(location, endpoint_url)
    queued: dict[Path, list[tuple[Path, S3Location]]] = {}
    for path in paths:
        path = path.resolve()
        if resume and (path / JOURNAL_NAME).is_file() and not (path / METADATA_FILENAME).exists():
            queued.setdefault(path / JOURNAL_NAME, [])
            continue
        files = bag_files(path)
        queued.setdefault(path.parent / JOURNAL_NAME, []).extend((file, location.child(path.name)) for file in files)
    report = UploadReport()
    for journal_path, files in queued.items():
        fd = lock_journal(journal_path, wait=False)
        if fd is None:
            waiting(journal_path)
            fd = lock_journal(journal_path, wait=True)
        journal = UploadJournal(journal_path)
        try:
            ids = [journal.enqueue(file, location.uri, endpoint_url, target.bucket, target.key(file.name),
                                   delete_after) for file, target in files]
            _drain(journal, None if resume else set(ids), max_rate, report, progress)
        finally:
            journal.close()
            os.close(fd)
    return report


def _drain(journal: UploadJournal, only: set[int] | None, max_rate: float, report: UploadReport,
           progress: Callable[[Entry, int], None]) -> None:
    def finished(entry: Entry, done: Transferred) -> None:
        (report.already_there if done.already_there else report.uploaded).append(str(entry.local))
        report.reused += done.reused

    def sent(entry: Entry, size: int) -> None:  # every request, those of an attempt that failed later too
        report.sent += size
        progress(entry, size)

    uploader = Uploader(journal, max_rate, threading.Event(), finished, sent, only)
    retry = FIRST_RETRY
    for attempt in range(ATTEMPTS):
        failure = uploader.drain()
        if failure is None:
            return
        if failure.permanent or attempt == ATTEMPTS - 1:
            raise failure
        time.sleep(retry)
        retry *= 2
