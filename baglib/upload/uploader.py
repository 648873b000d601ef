"""Working through a journal: each pending file uploaded and verified, in order; then, if asked, deleted here.

Strictly in order: the head of the queue blocks the rest, so a bag's ``metadata.yaml`` (queued when the bag was
closed, after its files) is uploaded only once every file before it is verified, and in the store a bag is
complete exactly when its ``metadata.yaml`` is there. A file that fails is retried by the caller after a
back-off; its error is in the journal for ``~/get_stats``. A file deleted here before it was verified (circular
recording, a person) is marked lost and counted, and the queue goes on.
"""
from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

from baglib.format.metadata import METADATA_FILENAME
from baglib.upload.client import UploadError, describe, make_client
from baglib.upload.journal import Entry, UploadJournal
from baglib.upload.throttle import Throttle
from baglib.upload.transfer import FileUpload, Interrupted, Transferred

#: The upload rate reported is the bytes sent over this many seconds.
RATE_WINDOW = 5.0


class Uploader:
    """Uploads what ``journal`` holds; ``stop`` ends the work between two requests."""

    def __init__(self, journal: UploadJournal, max_rate: float = 0.0, stop: threading.Event | None = None,
                 on_file: Callable[[Entry, Transferred], None] = lambda entry, done: None,
                 on_progress: Callable[[Entry, int], None] = lambda entry, sent: None,
                 only: Collection[int] | None = None) -> None:
        """``on_file``: after each file verified; ``on_progress``: after each request, with the bytes it sent;
        ``only``: the entries to upload (None: the whole queue)."""
        self.journal = journal
        self.only = only
        self.on_progress = on_progress
        self.stop = stop or threading.Event()
        self.throttle = Throttle(max_rate, self.stop)
        self.on_file = on_file
        self._clients: dict[str, Any] = {}
        self._sent: collections.deque[tuple[float, int]] = collections.deque()
        self._last_report = 0.0

    def drain(self) -> UploadError | None:
        """Upload until the queue is empty (None), ``stop`` is set (None) or a file fails (its error)."""
        while not self.stop.is_set():
            entry = self.journal.next_pending(self.only)
            if entry is None:
                return None
            try:
                done = FileUpload(self._client(entry.endpoint), self.journal, entry, self.throttle,
                                  lambda sent, entry=entry: self._progress(entry, sent)).run()
            except Interrupted:
                return None
            except FileNotFoundError:
                self.journal.finish(entry.id, "lost", f"{entry.local} was deleted before it was uploaded")
                continue
            except Exception as error:  # noqa: BLE001 - any failure of one file is reported, then retried
                failure = describe(error, f"uploading {entry.local.name} to s3://{entry.bucket}/{entry.key}")
                if not failure.permanent:
                    self._clients.pop(entry.endpoint, None)  # a fresh connection pool for the retry
                self.journal.report(entry.uri, 0.0, str(failure))
                return failure
            self._finished(entry, done)
        return None

    def _client(self, endpoint: str) -> Any:
        if endpoint not in self._clients:
            self._clients[endpoint] = make_client(endpoint)
        return self._clients[endpoint]

    def _finished(self, entry: Entry, done: Transferred) -> None:
        self.journal.finish(entry.id, "verified")
        if entry.delete_after:
            entry.local.unlink(missing_ok=True)
            if entry.local.name == METADATA_FILENAME:
                _remove_if_empty(entry.local.parent)
            self.journal.mark_deleted(entry.local)
        self.journal.report(entry.uri, self._rate(), "")
        self.on_file(entry, done)

    def _progress(self, entry: Entry, sent: int) -> None:
        self.on_progress(entry, sent)
        now = time.monotonic()
        self._sent.append((now, sent))
        if now - self._last_report >= 1.0:
            self._last_report = now
            self.journal.report(entry.uri, self._rate(), "")

    def _rate(self) -> float:
        now = time.monotonic()
        while self._sent and now - self._sent[0][0] > RATE_WINDOW:
            self._sent.popleft()
        return sum(sent for _, sent in self._sent) / RATE_WINDOW


def _remove_if_empty(directory: Path) -> None:
    """A bag directory all of whose files were uploaded and deleted goes too (but not one holding other files)."""
    try:
        directory.rmdir()
    except OSError:
        pass
