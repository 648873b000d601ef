"""``upload.*``: every file a recorder closes goes to S3-compatible object storage, ``metadata.yaml`` last.

Parameters: ``upload.uri`` (``s3://BUCKET/PREFIX``; empty: off), ``upload.endpoint_url`` (any S3-compatible store;
empty: the AWS configuration), ``upload.delete_after`` (delete each file here once its remote copy is verified)
and ``upload.max_rate`` (bytes/s, 0: unlimited). Credentials come from the AWS chain, never from a parameter.

The recorder only queues: a file closed at a split goes into the journal next to the bag (on a thread of this
module's, off the writer thread), and a finalized bag's ``metadata.yaml`` after all its files. A bag closed late, by
a writer the unload gave up on, goes into the journal after the recorder is gone, on the writer's thread. The
uploads themselves run in the container's upload process (components/recorder/upload_process.py,
baglib/upload/worker.py), which outlives an unloaded recorder until its queue is done. The upload state is in
``~/get_stats`` (``upload``), on ``/diagnostics`` (the recorder's, then the container's for an unloaded one) and so
in ``top`` and ``record status``. Files already verified in the store are the first the disk guard may take back
(:meth:`reclaim`).
"""
from __future__ import annotations

import queue
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rclpy.node import Node

from baglib.format.metadata import METADATA_FILENAME
from baglib.read.metadata_read import load_metadata
from baglib.upload.journal import JOURNAL_NAME, UploadJournal
from baglib.upload.location import S3Location, parse_s3_uri
from components.node_parameters import declare_defaults
from components.recorder import upload_process

DEFAULTS: dict[str, Any] = {"upload.uri": "", "upload.endpoint_url": "", "upload.delete_after": False,
                            "upload.max_rate": 0}
_KINDS = {"upload.max_rate": float}


@dataclass(frozen=True)
class UploadOptions:
    location: S3Location
    endpoint_url: str
    delete_after: bool
    max_rate: float


def declare_upload_options(node: Node) -> UploadOptions | None:
    """Declare ``upload.*`` on ``node``; the options (None: upload.uri is empty); ValueError on bad input."""
    values = declare_defaults(node, DEFAULTS, _KINDS)
    if not values["upload.uri"]:
        return None
    if values["upload.max_rate"] < 0:
        raise ValueError(f"parameter 'upload.max_rate' must be >= 0 bytes/s (0: unlimited), not "
                         f"{values['upload.max_rate']}")
    endpoint = values["upload.endpoint_url"]
    if endpoint and not endpoint.startswith(("http://", "https://")) or "@" in endpoint:
        raise ValueError(f"parameter 'upload.endpoint_url' must be an http:// or https:// URL without credentials, "
                         f"not {endpoint!r}")
    return UploadOptions(parse_s3_uri(values["upload.uri"]), endpoint, bool(values["upload.delete_after"]),
                         float(values["upload.max_rate"]))


class BagUploads:
    """The uploads of one recorder's bags (see module docstring)."""

    def __init__(self, options: UploadOptions) -> None:
        self.options = options
        self._journals: dict[Path, UploadJournal] = {}
        self._held: list[Path] = []  # the journals whose upload process the recorder holds until close
        self._lock = threading.Lock()
        self._closed = False
        self._queue: queue.SimpleQueue[tuple[Path, list[Path]] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="upload_queue", daemon=True)
        self._thread.start()

    # --- queueing ---------------------------------------------------------------------------------------
    def file_closed(self, path: Path) -> None:
        """A bag file was closed (a split): queue it. Called on the writer's threads: returns at once."""
        self._put(path.parent, [path])

    def bag_closed(self, bag: Path) -> None:
        """A bag was finalized: queue what of it is not queued yet, then its ``metadata.yaml``."""
        try:
            listed = [bag / name for name in load_metadata(bag).relative_file_paths]
        except Exception:  # noqa: BLE001 - an unfinalized bag: its closed files are queued, its metadata is not
            return
        self._put(bag, [*listed, bag / METADATA_FILENAME])

    def _put(self, bag: Path, files: list[Path]) -> None:
        """Queue ``files`` of ``bag``; once the recorder is gone (:meth:`close`), journal them on this thread,
        holding the journal's upload process meanwhile (started again if it finished)."""
        with self._lock:
            if not self._closed:
                self._queue.put((bag, files))
                return
            if bag.parent not in self._journals:
                self._journals[bag.parent] = UploadJournal(bag.parent / JOURNAL_NAME)
            journal = self._journals[bag.parent]
        upload_process.acquire(journal.path, self.options.max_rate)
        try:
            self._enqueue(journal, bag, files)
        finally:
            upload_process.release(journal.path)

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            bag, files = item
            self._enqueue(self._journal(bag.parent), bag, files)

    def _enqueue(self, journal: UploadJournal, bag: Path, files: list[Path]) -> None:
        location = self.options.location.child(bag.name)
        for path in files:
            journal.enqueue(path, self.options.location.uri, self.options.endpoint_url, location.bucket,
                            location.key(path.name), self.options.delete_after)
        upload_process.wake(journal.path)

    def _journal(self, directory: Path) -> UploadJournal:
        """The journal of ``directory``, its upload process taken on first use until :meth:`close`."""
        with self._lock:
            if directory not in self._journals:
                journal = self._journals[directory] = UploadJournal(directory / JOURNAL_NAME)
                upload_process.acquire(journal.path, self.options.max_rate)
                self._held.append(journal.path)
                upload_process.wake(journal.path)  # what a previous container left in it
            return self._journals[directory]

    def open(self, bag: Path) -> None:
        """A bag is starting at ``bag``: its directory's journal is opened and its upload process started (so
        what an earlier container left there is resumed now, not at the first split)."""
        self._put(bag, [])

    def close(self) -> None:
        """The recorder is going: let go of the upload processes once the queue is journaled (they finish it);
        a bag closed later is journaled by its writer's thread (:meth:`_put`)."""
        with self._lock:
            self._closed = True
            self._queue.put(None)
        self._thread.join()
        with self._lock:
            for path in self._held:
                upload_process.release(path)

    # --- state ------------------------------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """The upload state for ``~/get_stats``: files and bytes pending, rate, last error, complete, ..."""
        with self._lock:
            journals = list(self._journals.values())
        summary: dict[str, Any] = {"uri": self.options.location.uri, "files_pending": 0, "bytes_pending": 0,
                                   "files_uploaded": 0, "bytes_sent": 0, "bytes_reused": 0, "verify_mismatches": 0,
                                   "deleted_before_upload": 0, "rate": 0.0, "last_error": "", "complete": True}
        for journal in journals:
            part = journal.summary(self.options.location.uri)
            for key in ("files_pending", "bytes_pending", "files_uploaded", "bytes_sent", "bytes_reused",
                        "verify_mismatches", "deleted_before_upload", "rate"):
                summary[key] += part[key]
            summary["last_error"] = summary["last_error"] or part["last_error"]
            summary["complete"] = summary["complete"] and part["complete"]
        summary["running"] = any(upload_process.running(journal.path) for journal in journals)
        return summary

    def reclaim(self, needed: int) -> int:
        """Delete files verified in the store, oldest first, until ``needed`` bytes are freed; bytes freed."""
        freed = 0
        with self._lock:
            journals = list(self._journals.values())
        for journal in journals:
            for path in journal.verified_files():
                if freed >= needed:
                    return freed
                try:
                    size = path.stat().st_size
                    path.unlink()
                except FileNotFoundError:
                    size = 0
                journal.mark_deleted(path)
                freed += size
        return freed


def upload_values(stats: Mapping[str, Any]) -> dict[str, str]:
    """The upload state as /diagnostics values (``top`` shows them)."""
    return {"upload": "complete" if stats["complete"] else "pending",
            "upload pending (files)": str(stats["files_pending"]),
            "upload pending (MB)": f"{stats['bytes_pending'] / 1e6:.1f}",
            "upload rate (MB/s)": f"{stats['rate'] / 1e6:.2f}",
            "upload error": stats["last_error"],
            "deleted before upload": str(stats["deleted_before_upload"])}
