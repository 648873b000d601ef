"""Reading one ``.db3`` storage file, in each schema rosbag2's sqlite3 plugin has written.

The schema versions (rosbag2_storage_sqlite3 ``sqlite_storage.cpp``, ``read_db_schema_version``):
1 (before Foxy) ``topics`` without ``offered_qos_profiles``; 2 (Foxy, Galactic) with it; 3 (Humble)
adds the ``schema`` table (version, ROS distro) and the ``metadata`` table (the bag's metadata YAML);
4 (Iron, Jazzy) adds ``topics.type_description_hash`` and the ``message_definitions`` table. Every
version has ``messages(id, topic_id, timestamp, data)`` indexed by timestamp, which is the receive
time; there is no publish time.

Messages come out ordered by (timestamp, id): the order of ``timestamp_idx`` (sqlite keys every index
by the row id last), so a start time is a seek in that index and the order needs no sort.

Reading never writes next to the file, so bags on read-only media read as well as any. A database in
rollback-journal mode (what this project and ``rosbags`` write, and rosbag2 by default) is opened
``mode=ro``: that creates no file, keeps sqlite's locking (a writer may still be at work on the file) and
refuses a hot journal (``SQLITE_READONLY_ROLLBACK``). A database in WAL mode (rosbag2's ``resilient``
preset) cannot be opened that way without sqlite creating ``-wal`` and ``-shm`` files, which a read-only
connection then leaves behind, and where it may not create them it cannot open the file at all. Such a
database is opened ``immutable=1`` (no locks, no side files, the database file is taken as the whole
database), which is right only when its log holds nothing: a log with frames (a writer killed, or still at
work) is refused with the ``bag recover`` hint rather than read without its rows or replayed through a
``-shm`` file.
"""
from __future__ import annotations

import logging
import sqlite3
import urllib.parse
from collections.abc import Collection, Iterator
from pathlib import Path

from baglib.format.bag_files import RECOVER_COMMAND
from baglib.format.metadata import parse_qos_profiles
from baglib.format.service_events import service_type
from baglib.read.storage_reader import BagReadError, FileTopic, RawMessage

__all__ = ["SqliteReader"]

_log = logging.getLogger(__name__)
_MAGIC = b"SQLite format 3\0"
#: The database header's file format write and read versions in WAL mode (1, 1 in rollback-journal mode).
_WAL_VERSIONS = b"\x02\x02"
_WAL_VERSIONS_OFFSET = 18
#: A write-ahead log's header; frames follow it.
_WAL_HEADER_SIZE = 32


def _definition(definitions: dict[str, tuple[str, str]], type_name: str) -> tuple[str, str] | None:
    """The recorded definition of ``type_name``. rosbag2 stores a service event topic's (``pkg/srv/X_Event``)
    under the service type ``pkg/srv/X`` (``SequentialWriter::create_topic`` looks the text up by that name);
    this project's writer under the event type. Either is found."""
    if type_name in definitions:
        return definitions[type_name]
    try:
        return definitions.get(service_type(type_name))
    except ValueError:  # not a service event type
        return None


class SqliteReader:
    """One sqlite3 database open read-only; its messages may be read from several threads."""

    storage_id = "sqlite3"

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            with open(path, "rb") as file:
                header = file.read(_WAL_VERSIONS_OFFSET + len(_WAL_VERSIONS))
        except OSError as error:
            raise BagReadError(f"cannot open {path}: {error.strerror}") from error
        if not header.startswith(_MAGIC):
            raise BagReadError(f"{path} is not an SQLite3 database")
        self._db = self._connect(wal_mode=header[_WAL_VERSIONS_OFFSET:] == _WAL_VERSIONS)
        try:
            self._read_schema()
        except sqlite3.Error as error:
            self.close()
            raise BagReadError(f"{path} is not a readable rosbag2 database: {error}") from error
        except BaseException:
            self.close()
            raise

    def _connect(self, wal_mode: bool) -> sqlite3.Connection:
        """A read-only connection that creates no file next to the database (see the module's docstring)."""
        log = self._side_file("wal")
        if wal_mode and log.is_file() and log.stat().st_size > _WAL_HEADER_SIZE:
            raise BagReadError(f"cannot read {self.path}: its write-ahead log {log.name} holds changes the "
                               f"database file does not (a writer was killed, or still writes it); if no writer "
                               f"has it open, run `{RECOVER_COMMAND}` on the bag")
        uri = f"file:{urllib.parse.quote(str(self.path.resolve()))}?mode=ro{'&immutable=1' if wal_mode else ''}"
        try:
            db = sqlite3.connect(uri, uri=True, check_same_thread=False)
            db.execute("SELECT count(*) FROM sqlite_master").fetchone()
            return db
        except sqlite3.Error as error:
            hint = ""
            if self._side_file("journal").exists():
                hint = f" (a crash left its journal: run `{RECOVER_COMMAND}` on the bag)"
            raise BagReadError(f"cannot read {self.path}: {error}{hint}") from error

    def _side_file(self, kind: str) -> Path:
        """The ``-wal`` or ``-journal`` file sqlite keeps next to the database."""
        return self.path.with_name(f"{self.path.name}-{kind}")

    def _read_schema(self) -> None:
        tables = {name for (name,) in self._db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if not {"topics", "messages"} <= tables:
            raise BagReadError(f"{self.path} is not a rosbag2 database (no topics and messages tables)")
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(topics)")}
        self.ros_distro = ""
        if "schema" in tables:
            row = self._db.execute("SELECT schema_version, ros_distro FROM schema").fetchone()
            self.schema_version, self.ros_distro = (int(row[0]), str(row[1] or "")) if row else (3, "")
        else:
            self.schema_version = 2 if "offered_qos_profiles" in columns else 1
        self.serialized_metadata = ""
        if "metadata" in tables:
            row = self._db.execute("SELECT metadata FROM metadata ORDER BY id DESC LIMIT 1").fetchone()
            self.serialized_metadata = str(row[0]) if row else ""
        definitions: dict[str, tuple[str, str]] = {}
        if "message_definitions" in tables:
            for type_name, encoding, text in self._db.execute(
                    "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions ORDER BY id"):
                if encoding and encoding != "unknown":  # an empty text describes an empty message
                    definitions.setdefault(type_name, (encoding, text))
        qos = "offered_qos_profiles" if "offered_qos_profiles" in columns else "''"
        type_hash = "type_description_hash" if "type_description_hash" in columns else "''"
        self.topics = [
            FileTopic(topic_id, name, type_name, serialization_format, self._profiles(name, profiles),
                      type_hash_value or "", _definition(definitions, type_name))
            for topic_id, name, type_name, serialization_format, profiles, type_hash_value in self._db.execute(
                f"SELECT id, name, type, serialization_format, {qos}, {type_hash} FROM topics ORDER BY id")]

    def _profiles(self, topic: str, stored: str) -> tuple[dict, ...]:
        try:
            return tuple(parse_qos_profiles(stored))
        except ValueError as error:
            _log.warning("%s: topic %s: %s; its QoS profiles are left out", self.path, topic, error)
            return ()

    # --- the StorageReader interface ----------------------------------------------------------

    def time_range(self) -> tuple[int, int] | None:
        first, last = self._query("SELECT min(timestamp), max(timestamp) FROM messages").fetchone()
        return None if first is None else (first, last)

    def message_counts(self) -> dict[int, int]:
        return dict(self._query("SELECT topic_id, count(*) FROM messages GROUP BY topic_id").fetchall())

    def messages(self, keys: Collection[int] | None, start_ns: int | None, stop_ns: int | None
                 ) -> Iterator[RawMessage]:
        wanted = {topic.key for topic in self.topics} if keys is None else set(keys)
        if not wanted:
            return
        conditions, parameters = [f"topic_id IN ({', '.join('?' * len(wanted))})"], list(wanted)
        if start_ns is not None:
            conditions.append("timestamp >= ?")
            parameters.append(start_ns)
        if stop_ns is not None:
            conditions.append("timestamp < ?")
            parameters.append(stop_ns)
        cursor = self._query(
            f"SELECT topic_id, timestamp, data FROM messages WHERE {' AND '.join(conditions)}"
            " ORDER BY timestamp, id", parameters)
        try:
            for topic_id, timestamp, data in cursor:
                yield topic_id, timestamp, timestamp, data
        except sqlite3.Error as error:
            raise BagReadError(f"cannot read {self.path}: {error}") from error
        finally:
            cursor.close()

    def close(self) -> None:
        self._db.close()

    def _query(self, sql: str, parameters: Collection[int] = ()) -> sqlite3.Cursor:
        try:
            return self._db.execute(sql, tuple(parameters))
        except sqlite3.Error as error:
            raise BagReadError(f"cannot read {self.path}: {error}") from error
