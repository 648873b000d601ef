"""One ``.db3`` storage file with rosbag2's sqlite3 schema, version 4.

Messages are buffered and inserted in batches, one transaction each: a transaction per message
would cost a journal write per message. Each batch is atomic, so after a failed write (disk full)
the database holds exactly the committed batches and is closed cleanly. No ``-wal`` file is left
behind: ``rosbags`` opens the database read-only and immutable and would never see rows that are
still in a write-ahead log.
"""
from __future__ import annotations

import contextlib
import os
import errno
import sqlite3
from pathlib import Path

from baglib.format.cdr_fast import CdrData
from baglib.format.message_definitions import UNDESCRIBED, type_hash_of_definition
from baglib.format.durable import fsync_directory
from baglib.format.metadata import METADATA_VERSION, ROS_DISTRO, FileInfo, TopicInfo, serialize_qos_profiles

__all__ = ["SQLITE_PRESETS", "SqliteStorage", "create_tables"]

SCHEMA_VERSION = 4
_SCHEMA = f"""
CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, ros_distro TEXT NOT NULL);
CREATE TABLE metadata(id INTEGER PRIMARY KEY, metadata_version INTEGER NOT NULL,
  metadata TEXT NOT NULL);
CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL,
  serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL,
  type_description_hash TEXT NOT NULL);
CREATE TABLE message_definitions(id INTEGER PRIMARY KEY, topic_type TEXT NOT NULL,
  encoding TEXT NOT NULL, encoded_message_definition TEXT NOT NULL,
  type_description_hash TEXT NOT NULL);
CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL,
  timestamp INTEGER NOT NULL, data BLOB NOT NULL);
CREATE INDEX timestamp_idx ON messages (timestamp ASC);
INSERT INTO schema(schema_version, ros_distro) VALUES ({SCHEMA_VERSION}, '{ROS_DISTRO}');
"""

#: rosbag2's sqlite3 presets as (journal_mode, synchronous). Both keep the rollback journal on
#: disk (rosbag2's default keeps it in memory, so a crash mid-transaction can corrupt the file).
#: ``resilient`` also fsyncs every commit, so a power loss costs at most the batch in flight.
#: rosbag2 uses a write-ahead log for it, but a log that cannot be checkpointed (disk full) keeps
#: rows that ``rosbags`` never sees; a synced rollback journal gives the same durability.
SQLITE_PRESETS: dict[str, tuple[str, str]] = {
    # Default: the journal and database are synced at the critical moments of each commit (commits are
    # batched, at least every storage.flush_interval), so a power loss cannot corrupt the file; "none" is
    # the old unsynced mode (fastest; consistent after a process crash, not after a power loss).
    "": ("DELETE", "NORMAL"),
    "none": ("DELETE", "OFF"),
    "resilient": ("DELETE", "FULL"),
}



def create_tables(db: sqlite3.Connection) -> None:
    """Create rosbag2's tables (schema version 4) in an empty database; shared with ``bag recover``."""
    for statement in _SCHEMA.split(";"):
        if statement.strip():
            db.execute(statement)


# A batch is committed when it holds this many bytes or messages.
_BATCH_BYTES = 8 * 1024 * 1024
_BATCH_MESSAGES = 1000

# sqlite result codes that mean the disk or file cannot grow.
_FULL_CODES = {"SQLITE_FULL": errno.ENOSPC, "SQLITE_TOOBIG": errno.EFBIG}


def _fsync_files(*paths: Path) -> None:
    """fsync each of ``paths`` that exists (through a descriptor of our own: sqlite3 does not expose its)."""
    for path in paths:
        try:
            fd = os.open(path, os.O_RDONLY)
        except FileNotFoundError:
            continue
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _os_error(error: sqlite3.Error, path: Path) -> OSError:
    """The sqlite error as the ``OSError`` a file write would have raised."""
    name = getattr(error, "sqlite_errorname", "")
    code = _FULL_CODES.get(name, errno.EIO)
    return OSError(code, f"sqlite3: {error}", str(path))


class SqliteStorage:
    """Writes one sqlite3 database; single-threaded (the bag writer serializes access).

    Messages wait in a batch until it is committed, so mutable buffers (``bytearray``, writable
    ``memoryview``) are copied when written; ``bytes`` and read-only views are kept as they are.
    """

    storage_id = "sqlite3"
    extension = ".db3"
    presets = SQLITE_PRESETS

    def __init__(self, path: Path, preset: str = "", serialized_metadata: str = "", gather_bytes: int = 0) -> None:
        """Create the database at ``path`` (which must not exist) with the empty tables.

        ``serialized_metadata`` is accepted for symmetry with MCAP; rosbag2 stores the bag
        metadata in sqlite only when closing. ``gather_bytes`` too: messages are copied into batches anyway.
        """
        del serialized_metadata, gather_bytes
        if preset not in SQLITE_PRESETS:
            raise ValueError(
                f"unknown sqlite3 storage preset profile {preset!r} "
                f"(valid: {', '.join(repr(name) for name in SQLITE_PRESETS)})"
            )
        journal_mode, synchronous = SQLITE_PRESETS[preset]
        self.path = path
        self.error: OSError | None = None
        self.readable = True
        # Claim the name first: sqlite3.connect would happily open an existing database.
        path.open("xb").close()
        try:
            # Autocommit mode: transactions are begun explicitly, one per batch.
            self._db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
        except sqlite3.Error as error:
            raise _os_error(error, path) from error
        try:
            self._db.execute(f"PRAGMA journal_mode={journal_mode}")
            self._db.execute(f"PRAGMA synchronous={synchronous}")
            with self._db:
                self._db.execute("BEGIN")
                create_tables(self._db)
        except sqlite3.Error as error:
            self._db.close()
            raise _os_error(error, path) from error
        self._topic_ids: dict[str, int] = {}
        self._defined_types: set[str] = set()
        self._batch: list[tuple[int, int, bytes | memoryview]] = []
        self._batch_topics: list[str] = []
        self._batch_bytes = 0
        self._counts: dict[str, int] = {}
        self._first_ns: int | None = None
        self._last_ns: int | None = None
        self._info: FileInfo | None = None

    @property
    def size(self) -> int:
        """Bytes in the database file plus the batch not yet committed."""
        return self.path.stat().st_size + self._batch_bytes

    def add_topic(self, topic: TopicInfo, definition: tuple[str, str]) -> None:
        """Insert the topic row and, once per type, its message definition row.

        The definition row carries the hash of its own text: the locally installed type's hash when the
        text is the installed type's (correct even when a publisher announced a different version of the
        type), else the topic's (a definition copied from another bag, with the hash recorded with it).
        A type described with :data:`~baglib.format.message_definitions.UNDESCRIBED` gets no row: rosbag2
        writes one with an empty encoding, which rosbags (0.11) cannot open a bag with; no row reads the same
        ("no definition") in rosbag2 and in every reader.
        """
        self._require_open()
        if topic.name in self._topic_ids:
            return
        encoding, text = definition
        definition_hash = type_hash_of_definition(topic.type, definition, topic.type_description_hash)
        try:
            with self._db:
                self._db.execute("BEGIN")
                cursor = self._db.execute(
                    "INSERT INTO topics (name, type, serialization_format, offered_qos_profiles,"
                    " type_description_hash) VALUES (?, ?, ?, ?, ?)",
                    (topic.name, topic.type, topic.serialization_format,
                     serialize_qos_profiles(topic.offered_qos_profiles), topic.type_description_hash),
                )
                if topic.type not in self._defined_types and definition != UNDESCRIBED:
                    self._db.execute(
                        "INSERT INTO message_definitions (topic_type, encoding,"
                        " encoded_message_definition, type_description_hash) VALUES (?, ?, ?, ?)",
                        (topic.type, encoding, text, definition_hash),
                    )
        except sqlite3.Error as error:
            raise self._fail(error) from error
        self._defined_types.add(topic.type)
        assert cursor.lastrowid is not None
        self._topic_ids[topic.name] = cursor.lastrowid
        self._counts[topic.name] = 0

    def write(
        self, topic: str, data: CdrData, log_time_ns: int, publish_time_ns: int
    ) -> None:
        """Queue one message (only the log time is stored); commits when the batch is full."""
        del publish_time_ns
        self._require_open()
        topic_id = self._topic_ids[topic]
        if not isinstance(data, bytes) and not (isinstance(data, memoryview) and data.readonly):
            data = bytes(data)
        self._batch.append((topic_id, log_time_ns, data))
        self._batch_topics.append(topic)
        self._batch_bytes += len(data)
        if len(self._batch) >= _BATCH_MESSAGES or self._batch_bytes >= _BATCH_BYTES:
            self._commit()

    def write_gathered(self) -> None:
        """Nothing to do: messages are copied into the open batch, which :meth:`flush` commits."""

    def flush(self) -> None:
        """Commit the open batch: a crash of the process cannot lose a message written before this call."""
        self._require_open()
        self._commit()

    def close(self, serialized_metadata: str = "") -> FileInfo:
        """Commit, store the bag metadata, leave no journal behind, fsync and describe what is stored.

        Never raises for I/O errors; the returned counts cover exactly the committed messages and
        :attr:`error` tells what went wrong.
        """
        if self._info is not None:
            return self._info
        try:
            if self.error is None:
                self._commit()
            if serialized_metadata:
                self._db.execute(
                    "INSERT INTO metadata (metadata_version, metadata) VALUES (?, ?)",
                    (METADATA_VERSION, serialized_metadata),
                )
        except (sqlite3.Error, OSError) as error:
            if self.error is None:
                self.error = error if isinstance(error, OSError) else _os_error(error, self.path)
        finally:
            with contextlib.suppress(sqlite3.Error):
                self._db.close()
            with contextlib.suppress(OSError):
                # before metadata.yaml can name this file; the directory first: the file's name, and the removal of
                # the rollback journal by the last commit, are durable once the file's fsync returns (a journal
                # that came back after a power loss would roll that committed transaction back)
                fsync_directory(self.path.parent)
                _fsync_files(self.path)
        self._info = FileInfo.from_log_times(self.path.name, self._first_ns, self._last_ns, self._counts)
        return self._info

    def _commit(self) -> None:
        if not self._batch:
            return
        try:
            with self._db:
                self._db.execute("BEGIN")
                self._db.executemany(
                    "INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)", self._batch
                )
        except sqlite3.Error as error:
            raise self._fail(error) from error
        for (_, log_time_ns, _), topic in zip(self._batch, self._batch_topics, strict=True):
            self._counts[topic] += 1
            if self._first_ns is None or log_time_ns < self._first_ns:
                self._first_ns = log_time_ns
            if self._last_ns is None or log_time_ns > self._last_ns:
                self._last_ns = log_time_ns
        self._clear_batch()

    def _clear_batch(self) -> None:
        self._batch = []
        self._batch_topics = []
        self._batch_bytes = 0

    def _fail(self, error: sqlite3.Error) -> OSError:
        """Drop the failed batch (its transaction was rolled back) and remember the error."""
        self._clear_batch()
        if self.error is None:
            self.error = _os_error(error, self.path)
        return self.error

    def _require_open(self) -> None:
        if self._info is not None:
            raise ValueError(f"{self.path} is closed")
        if self.error is not None:
            raise OSError(self.error.errno, f"earlier write failed: {self.error.strerror}", str(self.path))
