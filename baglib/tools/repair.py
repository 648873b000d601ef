"""``bag recover``: make a bag directory that a crash left unfinished readable again.

A recording killed by SIGKILL or a power cut leaves its last MCAP file without data end, summary and
footer (readers refuse it), a SQLite3 file possibly with a hot journal, and no ``metadata.yaml`` for
the current file (rosbag2 writes it only at a split or at the end). Recovering keeps everything
that is intact and provably complete:

* MCAP: every record up to the first damage (:mod:`.mcap_records` checks every chunk), with chunk
  message indexes, statistics and the summary rebuilt, as ``mcap recover`` does;
* SQLite3: every committed row, read by sqlite itself from a copy of the database and its journal
  or write-ahead log (so a hot journal is rolled back and a log replayed, as any sqlite client would);
* ``metadata.yaml`` (version 9) regenerated from the files: per topic its type, serialization
  format, offered QoS profiles and type hash from the MCAP channels / SQLite topics table, custom data
  from the files' own metadata or the old ``metadata.yaml``.

It is itself crash-safe: repaired files are written aside under temporary names in the same
directory, fsynced, and renamed over the originals (or the whole result renamed to ``-o OUT``); a
rerun after an interruption finishes or discards what the interrupted run left. Any file content
gives a report, never a traceback.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import sqlite3
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from mcap.opcode import Opcode

from baglib.format.bag_files import RECOVER_COMMAND, STORAGE_EXTENSIONS, storage_files
from baglib.tools.patch_journal import Patch, apply_all, finish_journals
from baglib.format.mcap_records import MAGIC, Scan, Totals, scan, summary_tail
from baglib.write.mcap_storage import METADATA_KEY, METADATA_NAME
from baglib.format.metadata import METADATA_FILENAME, SAFE_LOADER, BagMetadata, FileInfo, TopicInfo
from baglib.write.sqlite_storage import create_tables


__all__ = ["RECOVER_COMMAND", "FileReport", "RecoveryReport", "recover_bag", "storage_files"]

_SQLITE_MAGIC = b"SQLite format 3\0"
_TEMP = ".recover-tmp"        # suffix of a file or directory being written by a recover
_ASIDE = ".recover-aside"     # suffix of a SQLite journal moved aside while its database is replaced
_SQLITE_SIDE_FILES = ("-journal", "-wal", "-shm")
_COPY_BLOCK = 1 << 20
_ROW_BATCH = 1000
_MESSAGES_AFTER = "SELECT id, topic_id, timestamp, data FROM messages WHERE id > ? ORDER BY id LIMIT ?"
_FOOTER_LENGTH = 1 + 8 + 8 + 8 + 4


@dataclass
class FileReport:
    """What recovering one storage file did: ``action`` is ``intact``, ``repaired`` or ``left out``."""

    name: str
    action: str = "intact"
    messages: int = 0
    bytes_cut: int = 0
    reasons: list[str] = field(default_factory=list)

    def line(self) -> str:
        if self.action == "left out":
            return f"{self.name}: left out ({'; '.join(self.reasons)})"
        text = f"{self.name}: {self.action}, {self.messages} messages kept"
        if self.bytes_cut:
            text += f", {self.bytes_cut} bytes cut"
        return text + "".join(f"; {reason}" for reason in self.reasons)


@dataclass
class RecoveryReport:
    """The outcome of :func:`recover_bag`; ``readable`` says whether the result can be opened."""

    bag: Path
    output: Path
    storage: str = ""
    files: list[FileReport] = field(default_factory=list)
    metadata: BagMetadata | None = None
    error: str = ""

    @property
    def readable(self) -> bool:
        return self.metadata is not None and not self.error

    def text(self) -> str:
        lines = [f"Recovering {self.bag}" + (f" into {self.output}" if self.output != self.bag else "")
                 + (f" ({self.storage})" if self.storage else "") + ":"]
        lines += [f"  {report.line()}" for report in self.files]
        if self.error:
            lines.append(f"Not recovered: {self.error}")
        elif self.metadata is not None:
            lines.append(f"Wrote {self.output / METADATA_FILENAME}: {len(self.metadata.files)} files, "
                         f"{self.metadata.message_count} messages, {len(self.metadata.topics)} topics")
        return "\n".join(lines)


@dataclass
class _Recovered:
    """One file's recoverable content: its entry, topics and a writer of the repaired file."""

    report: FileReport
    info: FileInfo
    topics: list[TopicInfo]
    custom_data: dict[str, str] | None
    #: Writes the repaired file at the temporary path, given the bag's metadata to close it with;
    #: ``None`` when the file is intact (or was repaired in place already) and is kept as it is.
    write: Callable[[Path, str], None] | None
    #: The in-place repair, given the bag's metadata: a :class:`Patch` of the file, or ``None`` when only
    #: a copy can repair it (then ``write`` does).
    patch: Callable[[str], Patch | None] | None = None


def recover_bag(bag: str | os.PathLike[str], output: str | os.PathLike[str] | None = None) -> RecoveryReport:
    """Recover the bag directory ``bag`` in place, or into the new directory ``output``."""
    bag = Path(bag)
    out = Path(output) if output is not None else bag
    report = RecoveryReport(bag, out)
    if not bag.is_dir():
        report.error = f"{bag} is not a directory"
        return report
    if out != bag and out.exists():
        report.error = f"{out} exists (a recovered bag is never written into an existing path)"
        return report
    try:
        _finish_interrupted(bag)
        target = bag if out == bag else out.with_name(f".{out.name}{_TEMP}")
        if target != bag:
            shutil.rmtree(target, ignore_errors=True)
            target.mkdir(parents=True)
        try:
            _recover_into(bag, target, report)
            if report.readable and target != bag:
                _fsync_directory(target)
                target.rename(out)
                _fsync_directory(out.parent)
        finally:
            if target != bag:
                shutil.rmtree(target, ignore_errors=True)
    except OSError as error:
        report.error = f"{error.filename or bag}: {error.strerror or error}"
        report.metadata = None
        with contextlib.suppress(OSError):  # leave no half-written copy behind (a full disk stays full)
            _finish_interrupted(bag)
    return report


def _recover_into(bag: Path, target: Path, report: RecoveryReport) -> None:
    paths = storage_files(bag)
    kinds = {_storage_of(path) for path in paths}
    if not paths:
        report.error = f"no .mcap or .db3 files in {bag}"
        return
    if len(kinds) > 1:
        report.error = f"files of different storages ({', '.join(sorted(kinds))}) in one bag"
        return
    report.storage = kinds.pop()
    recovered = []
    for path in paths:
        if report.storage == "mcap":
            result = _recover_mcap(path)
        else:
            result = _recover_sqlite(path, target / f".{path.name}{_TEMP}", in_place=target == bag)
        report.files.append(result.report)
        if result.report.action != "left out":
            recovered.append(result)
    if not recovered:
        report.error = "no file holds anything recoverable"
        return
    metadata = _bag_metadata(bag, report.storage, recovered)
    serialized = metadata.to_yaml()
    written, patches = [], []
    for result in recovered:
        destination = target / result.info.path
        patch = result.patch(serialized) if target == bag and result.patch is not None else None
        if patch is not None:
            patches.append(patch)
        elif result.write is not None:
            temporary = target / f".{result.info.path}{_TEMP}"
            result.write(temporary, serialized)
            _fsync_file(temporary)
            written.append((temporary, destination))
        elif target != bag:
            shutil.copyfile(bag / result.info.path, destination)
            _fsync_file(destination)
    apply_all(patches)
    for temporary, destination in written:
        _replace(temporary, destination)
    metadata.write(target)
    report.metadata = metadata


def _bag_metadata(bag: Path, storage: str, recovered: list[_Recovered]) -> BagMetadata:
    """The regenerated ``metadata.yaml``: topics in order of first appearance, files in order."""
    topics: dict[str, TopicInfo] = {}
    custom_data = _old_custom_data(bag)
    for result in recovered:
        for topic in result.topics:
            topics.setdefault(topic.name, topic)
        custom_data = custom_data or result.custom_data
    return BagMetadata(storage, list(topics.values()), [result.info for result in recovered], custom_data)


def _old_custom_data(bag: Path) -> dict[str, str] | None:
    with contextlib.suppress(Exception):  # whatever the old file holds, it is only a hint
        document = _load((bag / METADATA_FILENAME).read_text())
        return _custom_data(document.get("rosbag2_bagfile_information", document))
    return None


def _custom_data(document: Any) -> dict[str, str] | None:
    custom = document.get("custom_data") if isinstance(document, dict) else None
    if isinstance(custom, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in custom.items()):
        return custom or None
    return None


def _load(text: str) -> Any:
    return yaml.load(text, Loader=SAFE_LOADER)  # noqa: S506 (a safe loader)


def _storage_of(path: Path) -> str:
    """The storage a file belongs to: by its magic, else by its extension."""
    with open(path, "rb") as file:
        start = file.read(len(_SQLITE_MAGIC))
    if start.startswith(MAGIC):
        return "mcap"
    if start == _SQLITE_MAGIC:
        return "sqlite3"
    return STORAGE_EXTENSIONS[path.suffix]


def _topic(report: FileReport, name: str, type_name: str, serialization_format: str, qos: Any,
           type_hash: str) -> TopicInfo | None:
    """The topic as the file describes it, or ``None`` (and a note) if the description is unusable."""
    with contextlib.suppress(yaml.YAMLError, TypeError):
        qos = _load(qos) if isinstance(qos, str) else qos
    profiles = qos if isinstance(qos, list) and all(isinstance(p, dict) for p in qos) else []
    try:
        return TopicInfo(name, type_name, serialization_format, profiles, type_hash)
    except (ValueError, TypeError, AttributeError) as error:
        report.reasons.append(f"topic {name!r} not listed in {METADATA_FILENAME}: {error}")
        return None


# --- MCAP ------------------------------------------------------------------------------------


def _recover_mcap(path: Path) -> _Recovered:
    report = FileReport(path.name)
    with open(path, "rb") as file:
        size = os.fstat(file.fileno()).st_size
        found = scan(file, size, check_chunks=True)
        intact = found.damage is None and found.data_end is not None and _summary_intact(file, size, found)
    if not found.start:
        report.action = "left out"
        report.reasons.append(found.damage.reason if found.damage else "no header")
        return _Recovered(report, FileInfo(path.name), [], None, None)
    totals = Totals.of(found.units)
    report.messages = sum(totals.counts.values())
    if not intact:
        report.action = "repaired"
        kept_end = max([found.start, *(unit.end for unit in found.units)])
        report.bytes_cut = size - kept_end
        if found.damage is not None:
            report.reasons.append(found.damage.reason)
        else:
            report.reasons.append("summary missing or damaged: rebuilt")
    topics = []
    for channel in sorted(found.channels.values(), key=lambda channel: channel.id):
        schema = found.schemas.get(channel.schema_id)
        topic = _topic(report, channel.topic, schema.name if schema else "", channel.message_encoding,
                       channel.metadata.get("offered_qos_profiles", ""),
                       channel.metadata.get("topic_type_hash", ""))
        if topic is not None and topic.name not in {known.name for known in topics}:
            topics.append(topic)
    counts: dict[str, int] = {}
    for channel_id, count in totals.counts.items():
        topic_name = found.channels[channel_id].topic if channel_id in found.channels else ""
        counts[topic_name] = counts.get(topic_name, 0) + count
    custom_data = None
    with contextlib.suppress(yaml.YAMLError, AttributeError):
        custom_data = _custom_data(_load(found.metadata.get(METADATA_NAME, {}).get(METADATA_KEY, "")))
    info = FileInfo.from_log_times(path.name, totals.first_ns, totals.last_ns, counts)

    def write(temporary: Path, serialized_metadata: str) -> None:
        _write_mcap(path, temporary, found, totals, serialized_metadata)

    def patch(serialized_metadata: str) -> Patch | None:
        return _mcap_patch(path, found, totals, serialized_metadata)

    return _Recovered(report, info, topics, custom_data, None if intact else write, None if intact else patch)


def _summary_intact(file: Any, size: int, found: Scan) -> bool:
    """Whether the file ends in a footer whose summary follows the data end and has a valid CRC."""
    if found.data_end is None or size < found.data_end + _FOOTER_LENGTH + len(MAGIC):
        return False
    file.seek(size - _FOOTER_LENGTH - len(MAGIC))
    trailer = file.read(_FOOTER_LENGTH + len(MAGIC))
    opcode, length, summary_start, _offsets, crc = struct.unpack_from("<BQQQI", trailer)
    if trailer[-len(MAGIC):] != MAGIC or opcode != Opcode.FOOTER or length != 20:
        return False
    if not found.data_end < summary_start < size - _FOOTER_LENGTH:
        return False  # no summary: readers that need one (rosbags) refuse the file
    file.seek(summary_start)
    summary = file.read(size - len(MAGIC) - 4 - summary_start)
    return crc == 0 or zlib.crc32(summary) == crc


def _mcap_patch(path: Path, found: Scan, totals: Totals, serialized_metadata: str) -> Patch | None:
    """The file repaired in place: cut after its last kept record (before the message indexes of its last chunk,
    which are rewritten) and closed with the rebuilt summary. Every record before the cut stays where it is, so
    the file's own message indexes must be the ones the scan rebuilt; ``None`` if they are not (a writer that
    orders them otherwise, or none at all): then only a copy repairs the file."""
    chunk_indexes, metadata_indexes = [], []
    last = found.units[-1] if found.units else None
    with open(path, "rb") as file:
        for unit in found.units:
            if unit is not last and unit.indexes is not None:
                file.seek(unit.record_end)
                if file.read(unit.end - unit.record_end) != unit.indexes:
                    return None
            chunk_index, metadata_index = unit.moved(unit.start)
            if chunk_index is not None:
                chunk_indexes.append(chunk_index)
            if metadata_index is not None:
                metadata_indexes.append(metadata_index)
    if last is None:
        cut, indexes = found.start, b""
    elif last.indexes is not None:
        cut, indexes = last.record_end, last.indexes
    else:
        cut, indexes = last.end, b""
    tail = indexes + summary_tail(
        cut + len(indexes), [found.schemas[key] for key in sorted(found.schemas)],
        [found.channels[key] for key in sorted(found.channels)],
        {METADATA_NAME: {METADATA_KEY: serialized_metadata}}, totals, chunk_indexes, metadata_indexes)
    return Patch.prepare(path, cut, tail)


def _write_mcap(source: Path, temporary: Path, found: Scan, totals: Totals, serialized_metadata: str) -> None:
    """Copy the kept records of ``source`` into ``temporary`` and append the rebuilt summary."""
    chunk_indexes, metadata_indexes = [], []
    with open(source, "rb") as src, open(temporary, "xb") as dst:
        _copy(src, dst, 0, found.start)
        for unit in found.units:
            chunk_index, metadata_index = unit.moved(dst.tell())
            if unit.indexes is None:
                _copy(src, dst, unit.start, unit.end)
            else:
                _copy(src, dst, unit.start, unit.record_end)
                dst.write(unit.indexes)
            if chunk_index is not None:
                chunk_indexes.append(chunk_index)
            if metadata_index is not None:
                metadata_indexes.append(metadata_index)
        dst.write(summary_tail(
            dst.tell(), [found.schemas[key] for key in sorted(found.schemas)],
            [found.channels[key] for key in sorted(found.channels)],
            {METADATA_NAME: {METADATA_KEY: serialized_metadata}}, totals, chunk_indexes, metadata_indexes,
        ))


def _copy(src: Any, dst: Any, start: int, end: int) -> None:
    src.seek(start)
    while start < end:
        block = src.read(min(_COPY_BLOCK, end - start))
        if not block:
            raise OSError(f"{src.name} shrank while being recovered")
        dst.write(block)
        start += len(block)


# --- SQLite3 ---------------------------------------------------------------------------------


def _recover_sqlite(path: Path, temporary: Path, in_place: bool = False) -> _Recovered:
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
            return _Recovered(report, info, topics, custom_data, None)
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
            return _Recovered(report, FileInfo(path.name), [], None, None)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    report.action = "repaired"
    # The new database is already at the temporary path (written while the rows were read).
    return _Recovered(report, info, topics, custom_data, lambda _temporary, _metadata: None)


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
    return [suffix for suffix in _SQLITE_SIDE_FILES if path.with_name(path.name + suffix).exists()]


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
    if len(header) < 100 or not header.startswith(_SQLITE_MAGIC):
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
            topic = _topic(report, *fields)
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
                custom_data = _custom_data(_load(text)) or custom_data
    finally:
        db.close()
    report.messages = sum(counts.values())
    return topics, FileInfo.from_log_times(name, first, last, counts), custom_data


# --- crash safety ----------------------------------------------------------------------------


def _replace(temporary: Path, destination: Path) -> None:
    """Rename a written file over ``destination``; a database's journal is moved aside meanwhile.

    A journal left next to the new database would be "rolled back" into it. The aside journal
    exists only while the complete temporary file does, so :func:`_finish_interrupted` knows
    whether to roll the replacement forward.
    """
    for suffix in _SQLITE_SIDE_FILES:
        side = destination.with_name(destination.name + suffix)
        if side.exists():
            side.rename(destination.with_name(f".{destination.name}{suffix}{_ASIDE}"))
    os.replace(temporary, destination)
    _fsync_directory(destination.parent)
    for suffix in _SQLITE_SIDE_FILES:
        destination.with_name(f".{destination.name}{suffix}{_ASIDE}").unlink(missing_ok=True)


def _finish_interrupted(bag: Path) -> None:
    """Complete a replacement or an in-place patch an interrupted recover began, and remove what it left
    half-written."""
    finish_journals(bag)
    for aside in bag.glob(f".*{_ASIDE}"):
        database = aside.name[1:-len(_ASIDE)]
        for suffix in _SQLITE_SIDE_FILES:
            database = database.removesuffix(suffix)
        temporary = bag / f".{database}{_TEMP}"
        if temporary.exists():  # complete (it was fsynced before the journal moved): finish
            _replace(temporary, bag / database)
        aside.unlink(missing_ok=True)
    for leftover in bag.glob(f".*{_TEMP}*"):
        if leftover.is_dir():
            shutil.rmtree(leftover, ignore_errors=True)
        else:
            leftover.unlink(missing_ok=True)


def _fsync_file(path: Path) -> None:
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def _fsync_directory(path: Path) -> None:
    _fsync_file(path)
