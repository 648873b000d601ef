"""Repairing a SQLite3 storage file a crash left unfinished: every committed row. A hot journal or a write-ahead
log is played back by sqlite itself, in the file when that is allowed; a database that stays damaged has its
readable rows copied into a new database with rosbag2's schema (read through a copy sqlite may roll back)."""
from __future__ import annotations

import contextlib
import os
import shutil
import sqlite3
import struct
from pathlib import Path
from typing import Any

import yaml

from baglib.format.metadata import FileInfo, TopicInfo
from baglib.tools.recovered import FileReport, Recovered, custom_data_of, load_yaml, topic_of
from baglib.write.sqlite_storage import create_tables

__all__ = ["SQLITE_MAGIC", "SQLITE_SIDE_FILES", "recover_sqlite"]

SQLITE_MAGIC = b"SQLite format 3\0"
SQLITE_SIDE_FILES = ("-journal", "-wal", "-shm")
_ROW_BATCH = 1000
_MESSAGES_AFTER = "SELECT id, topic_id, timestamp, data FROM messages WHERE id > ? ORDER BY id LIMIT ?"


def recover_sqlite(path: Path, temporary: Path, in_place: bool = False) -> Recovered:
    """The file as it is if intact; else, ``in_place``, sqlite's own recovery in the file (a hot journal rolled
    back, a log replayed) if that makes it intact; else the committed rows read (via a copy sqlite may roll back
    or replay) into ``temporary``."""
    report = FileReport(path.name)
    side_files = _side_files(path)
    intact = not side_files and _sqlite_intact(path)
    if not intact and in_place and ("-journal" in side_files or "-wal" in side_files):
        intact = _recovered_in_place(path, side_files, report)
        side_files = _side_files(path)
    if intact:
        with contextlib.suppress(sqlite3.Error, ValueError):  # else rebuilt, or left out with the reason
            topics, info, custom_data = _sqlite_content(_connect(f"file:{path}?mode=ro", uri=True),
                                                        path.name, report)
            return Recovered(report, info, topics, custom_data, None)
    work = temporary.with_name(temporary.name + ".work")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    try:
        copy = work / path.name
        shutil.copyfile(path, copy)
        for suffix in side_files:
            if suffix != "-shm":  # sqlite rebuilds the shared-memory index from the log
                shutil.copyfile(path.with_name(path.name + suffix), work / (path.name + suffix))
        if "-journal" in side_files:
            report.reasons.append("hot journal rolled back (the transaction in progress is discarded)")
        if "-wal" in side_files:
            report.reasons.append("write-ahead log replayed (its committed transactions are kept)")
        _cut_partial_page(copy, report)
        try:
            source = _connect(copy)
            try:
                # A file shorter than its header says is "malformed" unless sqlite may trust the
                # file size instead; nothing is written through this connection.
                source.execute("PRAGMA writable_schema=ON")
                source.execute("SELECT count(*) FROM sqlite_master").fetchone()  # applies journal / log
                _copy_rows(source, temporary, report)
            finally:
                source.close()
            topics, info, custom_data = _sqlite_content(sqlite3.connect(temporary), path.name, report)
        # IndexError: a topics table without a column; ValueError: a column name that is not UTF-8
        except (sqlite3.Error, IndexError, ValueError) as error:
            temporary.unlink(missing_ok=True)
            report.action = "left out"
            report.reasons.append(f"not a readable rosbag2 database: {error}")
            return Recovered(report, FileInfo(path.name), [], None, None)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    report.action = "repaired"
    # The new database is already at the temporary path (written while the rows were read).
    return Recovered(report, info, topics, custom_data, lambda _temporary, _metadata: None)


def _recovered_in_place(path: Path, side_files: list[str], report: FileReport) -> bool:
    """Let sqlite recover the database where it is from its journal or log, as any client opening it would
    (crash-safe by sqlite's own design, no second copy; sqlite plays back only a valid journal). True if the file
    is then intact and no journal or log is left; the reasons say what was done."""
    reasons = []
    if "-journal" in side_files:
        reasons.append("hot journal rolled back in place (the transaction in progress is discarded)")
    if "-wal" in side_files:
        reasons.append("write-ahead log replayed in place (its committed transactions are kept)")
    try:
        db = sqlite3.connect(path)
        try:
            db.execute("SELECT count(*) FROM sqlite_master").fetchone()  # rolls a hot journal back
            if "-wal" in side_files:
                db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
                db.execute("PRAGMA journal_mode=DELETE").fetchone()  # folds the log in and removes it
        finally:
            db.close()
    except sqlite3.Error:
        return False
    if _side_files(path) or not _sqlite_intact(path):
        return False
    report.action = "repaired"
    report.reasons += reasons
    return True


def _side_files(path: Path) -> list[str]:
    return [suffix for suffix in SQLITE_SIDE_FILES if path.with_name(path.name + suffix).exists()]


def _connect(database: str | Path, uri: bool = False) -> sqlite3.Connection:
    """A connection whose damaged text comes back with replacement characters instead of ending
    the reading with a ``UnicodeDecodeError``."""
    db = sqlite3.connect(database, uri=uri)
    db.text_factory = lambda data: data.decode(errors="replace")
    return db


def _sqlite_intact(path: Path) -> bool:
    """Whether sqlite reads the file as it is: whole pages, as many as its header says, checked
    (``integrity_check``: readers sort by the timestamp index, which ``quick_check`` does not compare).

    The size is checked first: a file cut inside its last page passes ``quick_check`` (sqlite reads
    the missing bytes as zeros), and rows there would come back silently cut.
    """
    page_size, pages = _sqlite_pages(path)
    if not page_size or path.stat().st_size != page_size * pages:
        return False
    try:
        db = _connect(f"file:{path}?mode=ro", uri=True)
        try:
            return db.execute("PRAGMA integrity_check").fetchall() == [("ok",)] and bool(
                db.execute("SELECT 1 FROM sqlite_master WHERE name = 'messages'").fetchone())
        finally:
            db.close()
    except sqlite3.Error:
        return False


def _sqlite_pages(path: Path) -> tuple[int, int]:
    """Page size and page count from the database header; (0, 0) without a valid header."""
    with open(path, "rb") as file:
        header = file.read(100)
    if len(header) < 100 or not header.startswith(SQLITE_MAGIC):
        return 0, 0
    page_size, = struct.unpack_from(">H", header, 16)
    pages, = struct.unpack_from(">I", header, 28)
    return (65536 if page_size == 1 else page_size), pages


def _cut_partial_page(copy: Path, report: FileReport) -> None:
    """Drop a page the file ends inside: sqlite would read its missing part as zeros, and rows in it
    could come back with their data silently cut."""
    page_size, _ = _sqlite_pages(copy)
    size = copy.stat().st_size
    if page_size and size % page_size:
        os.truncate(copy, size - size % page_size)
        report.bytes_cut += size % page_size
        report.reasons.append(f"file ends inside page {size // page_size + 1}: that page is dropped")


def _copy_rows(source: sqlite3.Connection, temporary: Path, report: FileReport) -> None:
    """Every readable row of ``source`` into a new database with rosbag2's schema, fsynced."""
    temporary.unlink(missing_ok=True)
    db = sqlite3.connect(temporary, isolation_level=None)
    try:
        db.execute("PRAGMA journal_mode=OFF")  # a temporary file: an interruption discards it anyway
        db.execute("BEGIN")
        create_tables(db)
        source.row_factory = sqlite3.Row
        tables = {row[0] for row in source.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        topic_ids = set()
        for row in source.execute("SELECT * FROM topics ORDER BY id"):
            columns = row.keys()
            db.execute("INSERT INTO topics VALUES (?, ?, ?, ?, ?, ?)", (
                row["id"], row["name"], row["type"], row["serialization_format"], row["offered_qos_profiles"],
                row["type_description_hash"] if "type_description_hash" in columns else ""))
            topic_ids.add(row["id"])
        if "message_definitions" in tables:
            db.executemany("INSERT INTO message_definitions VALUES (?, ?, ?, ?, ?)", (
                tuple(row) for row in source.execute(
                    "SELECT id, topic_type, encoding, encoded_message_definition, type_description_hash"
                    " FROM message_definitions")))
        if "metadata" in tables:
            db.executemany("INSERT INTO metadata VALUES (?, ?, ?)", (
                tuple(row) for row in source.execute("SELECT id, metadata_version, metadata FROM metadata")))
        source.row_factory = None
        db.executemany("INSERT INTO messages VALUES (?, ?, ?, ?)", _readable_messages(source, topic_ids, report))
        db.execute("COMMIT")
    finally:
        db.close()


def _readable_messages(source: sqlite3.Connection, topic_ids: set[int], report: FileReport) -> Any:
    """Rows in id order, past unreadable pages; rows that are not messages are skipped.

    Read in batches by id range: Python's cursor reads one row ahead, so the row before an
    unreadable page would be lost with the error. The batch that meets the error is read again row
    by row, and then reading resumes at the first id sqlite can reach again.
    """
    skipped = 0
    last_id = -(2**63)
    batch = _ROW_BATCH
    while True:
        try:
            rows = source.execute(_MESSAGES_AFTER, (last_id, batch)).fetchall()
            if rows and rows[-1][0] <= last_id:  # a damaged page sqlite did not notice
                raise sqlite3.DatabaseError("row ids out of order")
        except sqlite3.DatabaseError as error:
            if batch > 1:
                batch = 1
                continue
            resume = _next_readable(source, last_id)
            if resume is None:
                report.reasons.append(f"messages end after row {last_id}: {error} (rows after it cut)")
                break
            report.reasons.append(f"rows {last_id + 1}..{resume} unreadable: {error} (cut)")
            last_id = resume
            continue
        if not rows:
            break
        for row in rows:
            if row[0] <= last_id:  # ids must increase: anything else is damage
                skipped += 1
                continue
            last_id, topic_id, timestamp, data = row
            if topic_id in topic_ids and isinstance(timestamp, int) and isinstance(data, bytes):
                yield row
            else:
                skipped += 1
    if skipped:
        report.reasons.append(f"{skipped} damaged rows skipped")


def _next_readable(source: sqlite3.Connection, after: int) -> int | None:
    """The smallest id past ``after`` from which sqlite can seek on (``None``: nowhere)."""
    def readable(start: int) -> bool:
        try:
            rows = source.execute(_MESSAGES_AFTER, (start, 1)).fetchall()
            return not rows or rows[0][0] > start
        except sqlite3.DatabaseError:
            return False

    low, jump = after, 1
    while not readable(low + jump):  # doubling steps past the unreadable page ...
        low, jump = low + jump, jump * 2
        if low + jump >= 2**63:
            return None
    high = low + jump
    while high - low > 1:  # ... then back to where it ends
        middle = (low + high) // 2
        low, high = (low, middle) if readable(middle) else (middle, high)
    return high


def _sqlite_content(db: sqlite3.Connection, name: str, report: FileReport
                    ) -> tuple[list[TopicInfo], FileInfo, dict[str, str] | None]:
    """Topics, the file's entry and custom data of a (readable) rosbag2 database; closes ``db``."""
    try:
        names, topics = {}, []
        for topic_id, *fields in db.execute(
                "SELECT id, name, type, serialization_format, offered_qos_profiles, type_description_hash"
                " FROM topics ORDER BY id"):
            names[topic_id] = fields[0]
            topic = topic_of(report, *fields)
            if topic is not None:
                topics.append(topic)
        counts: dict[str, int] = {}
        first = last = None
        for topic_id, count, low, high in db.execute(
                "SELECT topic_id, count(*), min(timestamp), max(timestamp) FROM messages GROUP BY topic_id"):
            counts[names.get(topic_id, "")] = counts.get(names.get(topic_id, ""), 0) + count
            first = low if first is None else min(first, low)
            last = high if last is None else max(last, high)
        custom_data = None
        for (text,) in db.execute("SELECT metadata FROM metadata ORDER BY id"):
            with contextlib.suppress(yaml.YAMLError):
                custom_data = custom_data_of(load_yaml(text)) or custom_data
    finally:
        db.close()
    report.messages = sum(counts.values())
    return topics, FileInfo.from_log_times(name, first, last, counts), custom_data
