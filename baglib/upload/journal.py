"""The upload journal: what is to be uploaded, in order, and how far each upload got.

One SQLite database next to the bags (``upload_journal.sqlite3`` in the directory that holds them), shared by
the recorders that write there, the upload process that works through it and ``bag upload``. A row per file:
the local path, the target (URI, endpoint, bucket, key), its state, and for a multipart upload the upload id and
the part size; a row per part the server confirmed (number, ETag, size). So an upload cut by anything (a network
drop, a server restart, SIGKILL, a power cut) resumes from its last confirmed part: the journal is written with
``synchronous=FULL`` in WAL mode, and a part the journal lost is one the server lists again (``ListParts``).

States: ``pending`` (queued or under way), ``verified`` (the store holds the same bytes), ``deleted`` (verified,
then deleted here: ``upload.delete_after`` or the disk guard's reclaim), ``lost`` (the local file went away
before it was verified: circular recording or a person; counted as ``deleted_before_upload``).
"""
from __future__ import annotations

import contextlib
import sqlite3
import threading
import time
from collections.abc import Collection, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: The journal's file name, in the directory that holds the bags.
JOURNAL_NAME = "upload_journal.sqlite3"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS files(
  id INTEGER PRIMARY KEY, local TEXT NOT NULL, uri TEXT NOT NULL, endpoint TEXT NOT NULL,
  bucket TEXT NOT NULL, key TEXT NOT NULL, size INTEGER NOT NULL, delete_after INTEGER NOT NULL,
  state TEXT NOT NULL DEFAULT 'pending', upload_id TEXT, part_size INTEGER,
  sent INTEGER NOT NULL DEFAULT 0, reused INTEGER NOT NULL DEFAULT 0, mismatches INTEGER NOT NULL DEFAULT 0,
  error TEXT NOT NULL DEFAULT '', finished_ns INTEGER, UNIQUE(local, bucket, key));
CREATE TABLE IF NOT EXISTS parts(
  file_id INTEGER NOT NULL, number INTEGER NOT NULL, etag TEXT NOT NULL, size INTEGER NOT NULL,
  PRIMARY KEY(file_id, number));
CREATE TABLE IF NOT EXISTS uploader(
  uri TEXT PRIMARY KEY, rate REAL NOT NULL DEFAULT 0, error TEXT NOT NULL DEFAULT '', updated_ns INTEGER);
"""


@dataclass(frozen=True)
class Entry:
    """One file to upload, as the journal holds it."""

    id: int
    local: Path
    uri: str
    endpoint: str
    bucket: str
    key: str
    size: int
    delete_after: bool
    state: str
    upload_id: str | None
    part_size: int | None
    mismatches: int


class UploadJournal:
    """The journal at ``path`` (created if missing). Thread-safe; several processes may share it."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._db = sqlite3.connect(path, timeout=30.0, isolation_level=None, check_same_thread=False)
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.executescript(_SCHEMA)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    def _rows(self, query: str, *args: Any) -> list[tuple[Any, ...]]:
        with self._lock:
            return self._db.execute(query, args).fetchall()

    # --- the queue --------------------------------------------------------------------------------------
    def enqueue(self, local: Path, uri: str, endpoint: str, bucket: str, key: str, delete_after: bool) -> int:
        """Queue ``local`` (a closed file) for ``bucket``/``key``; its entry's id (the existing one if it is
        queued or done already). A file already gone (circular recording took it at once) is entered as lost."""
        try:
            size, state = local.stat().st_size, "pending"
        except FileNotFoundError:
            size, state = 0, "lost"
        with self._transaction() as db:
            db.execute("INSERT OR IGNORE INTO files(local, uri, endpoint, bucket, key, size, delete_after, state) "
                       "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                       (str(local), uri, endpoint, bucket, key, size, int(delete_after), state))
            return db.execute("SELECT id FROM files WHERE local = ? AND bucket = ? AND key = ?",
                              (str(local), bucket, key)).fetchone()[0]

    def next_pending(self, only: Collection[int] | None = None) -> Entry | None:
        """The oldest file not yet verified (files go in the order they were queued), among ``only`` if given."""
        rows = [row for row in self._rows(
            "SELECT id, local, uri, endpoint, bucket, key, size, delete_after, state, upload_id, part_size, "
            "mismatches FROM files WHERE state = 'pending' ORDER BY id") if only is None or row[0] in only][:1]
        if not rows:
            return None
        (id_, local, uri, endpoint, bucket, key, size, delete_after, state, upload_id, part_size,
         mismatches) = rows[0]
        return Entry(id_, Path(local), uri, endpoint, bucket, key, size, bool(delete_after), state, upload_id,
                     part_size, mismatches)

    def start_multipart(self, entry_id: int, upload_id: str | None, part_size: int | None) -> None:
        """Remember the multipart upload under way (None: there is none; its parts are forgotten too)."""
        with self._transaction() as db:
            db.execute("UPDATE files SET upload_id = ?, part_size = ? WHERE id = ?", (upload_id, part_size, entry_id))
            db.execute("DELETE FROM parts WHERE file_id = ?", (entry_id,))

    def confirm_part(self, entry_id: int, number: int, etag: str, size: int) -> None:
        """The server confirmed part ``number`` with ``etag`` (sent now: counted in the bytes sent)."""
        with self._transaction() as db:
            db.execute("INSERT OR REPLACE INTO parts VALUES (?, ?, ?, ?)", (entry_id, number, etag, size))
            db.execute("UPDATE files SET sent = sent + ? WHERE id = ?", (size, entry_id))

    def count_sent(self, entry_id: int, sent: int, reused: int) -> None:
        """Bytes sent in one request (a single PUT) and bytes the server already held (parts reused)."""
        with self._transaction() as db:
            db.execute("UPDATE files SET sent = sent + ?, reused = reused + ? WHERE id = ?", (sent, reused, entry_id))

    def mismatch(self, entry_id: int, error: str) -> None:
        """The remote copy did not verify: count it; the file is uploaded again, over that copy."""
        with self._transaction() as db:
            db.execute("UPDATE files SET mismatches = mismatches + 1, error = ?, upload_id = NULL WHERE id = ?",
                       (error, entry_id))
            db.execute("DELETE FROM parts WHERE file_id = ?", (entry_id,))

    def finish(self, entry_id: int, state: str, error: str = "") -> None:
        """The file left the queue: ``verified``, ``deleted`` or ``lost``."""
        with self._transaction() as db:
            db.execute("UPDATE files SET state = ?, error = ?, finished_ns = ? WHERE id = ?",
                       (state, error, time.time_ns(), entry_id))
            db.execute("DELETE FROM parts WHERE file_id = ?", (entry_id,))

    def mark_deleted(self, local: Path) -> None:
        """A verified file was deleted here (``upload.delete_after`` or reclaimed space)."""
        with self._transaction() as db:
            db.execute("UPDATE files SET state = 'deleted' WHERE local = ? AND state = 'verified'", (str(local),))

    def confirmed_parts(self, entry_id: int) -> dict[int, tuple[str, int]]:
        """The parts the journal holds as confirmed: number -> (ETag, size)."""
        return {number: (etag, size) for number, etag, size in
                self._rows("SELECT number, etag, size FROM parts WHERE file_id = ?", entry_id)}

    def verified_files(self) -> list[Path]:
        """Files verified in the store and still here, oldest first: the first a full disk may take back."""
        return [Path(local) for (local,) in
                self._rows("SELECT local FROM files WHERE state = 'verified' ORDER BY id")]

    def is_verified(self, local: Path) -> bool:
        return bool(self._rows("SELECT 1 FROM files WHERE local = ? AND state IN ('verified', 'deleted')",
                               str(local)))

    # --- what the uploader reports ------------------------------------------------------------------------
    def report(self, uri: str, rate: float, error: str) -> None:
        """The uploader's current rate (bytes/s) and last error ('' once an upload succeeds again)."""
        with self._transaction() as db:
            db.execute("INSERT OR REPLACE INTO uploader VALUES (?, ?, ?, ?)", (uri, rate, error, time.time_ns()))

    def summary(self, uri: str) -> dict[str, Any]:
        """The upload state of ``uri``: files and bytes pending, files uploaded, files lost, bytes sent and
        reused, verification mismatches, the rate, the last error and whether it is all complete."""
        rows = self._rows("SELECT state, COUNT(*), SUM(size), SUM(sent), SUM(reused), SUM(mismatches) FROM files "
                          "WHERE uri = ? GROUP BY state", uri)
        by_state = {state: (count, size or 0, sent or 0, reused or 0, mismatches or 0)
                    for state, count, size, sent, reused, mismatches in rows}
        deleting = self._rows("SELECT COUNT(*) FROM files WHERE uri = ? AND state = 'verified' AND delete_after",
                              uri)[0][0]  # verified, about to be deleted here: not complete until they are
        reporter = self._rows("SELECT rate, error FROM uploader WHERE uri = ?", uri)
        rate, error = reporter[0] if reporter else (0.0, "")
        pending = by_state.get("pending", (0, 0, 0, 0, 0))
        done = [by_state.get(state, (0, 0, 0, 0, 0)) for state in ("verified", "deleted")]
        return {
            "uri": uri,
            "files_pending": pending[0],
            "bytes_pending": pending[1],
            "files_uploaded": sum(counts[0] for counts in done),
            "bytes_sent": sum(counts[2] for counts in by_state.values()),
            "bytes_reused": sum(counts[3] for counts in by_state.values()),
            "verify_mismatches": sum(counts[4] for counts in by_state.values()),
            "deleted_before_upload": by_state.get("lost", (0,))[0],
            "rate": rate if pending[0] else 0.0,
            "last_error": error if pending[0] else "",
            "complete": pending[0] == 0 and deleting == 0,
        }


def summary_text(stats: Mapping[str, Any] | None) -> str:
    """A :meth:`UploadJournal.summary` in a few words (``-``: no upload), for ``top`` and ``record status``."""
    if not stats:
        return "-"
    if stats["last_error"]:
        return f"failing ({stats['files_pending']} files pending): {stats['last_error']}"
    if stats["complete"]:
        return f"complete ({stats['files_uploaded']} files)"
    return (f"{stats['files_pending']} files, {stats['bytes_pending'] / 1e6:.1f} MB pending, "
            f"{stats['rate'] / 1e6:.1f} MB/s")
