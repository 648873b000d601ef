"""An MCAP file as a sequence of complete top-level records: scanning one up to its first damage, and
the summary that makes such a sequence a file readers open.

A crash, a full disk or a bad copy cuts an MCAP file anywhere and may leave anything after the cut.
Both the writer's repair after a failed write (:mod:`.mcap_storage`) and ``bag recover``
(:mod:`.repair`) need the same answer: which records before the damage are whole and usable, what
their summary (statistics, chunk and metadata indexes) is, and where and why the file stops being
usable. This module is that one answer; the two callers differ only in what they do with it (cut the
file in place, or copy the records into a new one).

A chunk counts with the message indexes that follow it. Its indexes are rebuilt from its content
whenever that content is read (always for the last chunk, whose indexes may be cut short; for every
chunk when ``check_chunks`` asks for it), so the indexes of a kept chunk are always right.
"""
from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import BinaryIO

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    McapRecord,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

__all__ = ["MAGIC", "Damage", "InvalidRecord", "Scan", "Totals", "Unit", "decompress", "scan", "summary_tail"]

MAGIC = b"\x89MCAP0\r\n"
# opcode and record length: what precedes every record's body
_RECORD_START = struct.Struct("<BQ")
# Records allowed between the header and the data end; anything else there is damage.
_DATA_OPCODES = {Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.CHUNK, Opcode.MESSAGE_INDEX,
                 Opcode.ATTACHMENT, Opcode.METADATA, Opcode.DATA_END}
_NAMES = {opcode: opcode.name.lower().replace("_", " ") for opcode in Opcode}


@dataclass
class Unit:
    """A complete top-level record found in the file (a chunk counts with its message indexes).

    ``indexes`` are the chunk's message indexes rebuilt from its content, with offsets as if they
    followed the chunk record at ``record_end``; ``None`` when the file's own indexes were trusted.
    """

    start: int
    record_end: int
    end: int
    indexes: bytes | None = None
    crc: int = 0
    counts: dict[int, int] = field(default_factory=dict)
    first_ns: int | None = None
    last_ns: int | None = None
    chunk_index: ChunkIndex | None = None
    metadata_index: MetadataIndex | None = None

    def moved(self, position: int) -> tuple[ChunkIndex | None, MetadataIndex | None]:
        """The unit's index entries once its record starts at ``position`` (followed by ``indexes``)."""
        shift = position - self.start
        chunk_index = metadata_index = None
        if self.chunk_index is not None:
            chunk_index = replace(
                self.chunk_index, chunk_start_offset=self.chunk_index.chunk_start_offset + shift,
                message_index_offsets={channel: offset + shift for channel, offset
                                       in self.chunk_index.message_index_offsets.items()},
            )
        if self.metadata_index is not None:
            metadata_index = replace(self.metadata_index, offset=self.metadata_index.offset + shift)
        return chunk_index, metadata_index


@dataclass
class Damage:
    """Where the usable part of the file ends and why; ``lost_messages`` is a lower bound (``None``:
    unknown), since a chunk cut short holds more messages than its written part shows."""

    offset: int
    reason: str
    lost_messages: int | None = 0


@dataclass
class Scan:
    """Everything usable in a file, in order.

    ``start`` is where the records after the header begin (0 if even the header is incomplete);
    ``data_end`` the offset of the data end record, if the scan reached it; ``damage`` the first
    thing not kept (``None`` when the data section is complete). ``schemas`` and ``channels`` are
    those defined in the kept records that were read (top-level ones, and those in read chunks);
    ``metadata`` maps each metadata record's name to its latest content.
    """

    start: int = 0
    units: list[Unit] = field(default_factory=list)
    data_end: int | None = None
    damage: Damage | None = None
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)


@dataclass
class Totals:
    """Message counts per channel and the log time range of a list of units."""

    counts: dict[int, int]
    first_ns: int | None
    last_ns: int | None

    @classmethod
    def of(cls, units: Sequence[Unit]) -> Totals:
        counts: dict[int, int] = {}
        first: int | None = None
        last: int | None = None
        for unit in units:
            for channel_id, count in unit.counts.items():
                counts[channel_id] = counts.get(channel_id, 0) + count
            if unit.counts and unit.first_ns is not None and unit.last_ns is not None:
                first = unit.first_ns if first is None else min(first, unit.first_ns)
                last = unit.last_ns if last is None else max(last, unit.last_ns)
        return cls(counts, first, last)


class InvalidRecord(Exception):
    """A record that is complete but cannot be used; the message says why."""


def _parse(record_type: type[McapRecord], body: bytes) -> McapRecord:
    """The record parsed from exactly ``body``; garbage of any kind raises :class:`InvalidRecord`."""
    stream = ReadDataStream(io.BytesIO(body))
    try:
        record = record_type.read(stream)  # type: ignore[attr-defined]
    except Exception as error:  # the parser meets arbitrary bytes: struct, unicode, EOF errors...
        raise InvalidRecord(f"unreadable {record_type.__name__.lower()} record ({error})") from error
    if stream.count != len(body):
        raise InvalidRecord(f"{record_type.__name__.lower()} record of the wrong length")
    return record


def _name(opcode: int) -> str:
    return _NAMES.get(opcode, f"0x{opcode:02x}")  # type: ignore[call-overload]


def scan(file: BinaryIO, size: int, check_chunks: bool = False) -> Scan:
    """Read ``file`` (``size`` bytes) from the start up to its data end or first damage.

    With ``check_chunks`` every chunk is decompressed and parsed (and must be whole to be kept), and
    every message must name a known channel; otherwise only the last chunk is read, and the message
    indexes of the others are trusted (as the writer's repair does with the file it just wrote).
    """
    result = Scan()
    file.seek(0)
    if file.read(8) != MAGIC:
        reason = "file ends inside the magic" if size < 8 else "no MCAP magic at the start"
        result.damage = Damage(0, reason)
        return result
    start = file.read(9)
    if len(start) < 9 or start[0] != Opcode.HEADER or 17 + _RECORD_START.unpack(start)[1] > size:
        result.damage = Damage(8, "no complete header record")
        return result
    position = result.start = 17 + _RECORD_START.unpack(start)[1]
    chunk: Unit | None = None  # the latest chunk, while the message indexes after it are read
    buffer = _Buffer()
    while True:
        file.seek(position)
        head = file.read(9)
        if len(head) < 9:
            reason = f"file ends inside a record header at offset {position}" if head \
                else "file ends without a data end record"
            result.damage = Damage(position, reason)
            break
        opcode, length = _RECORD_START.unpack(head)
        end = position + 9 + length
        if opcode not in _DATA_OPCODES and opcode < 0x80:
            result.damage = Damage(position, f"invalid record (opcode 0x{opcode:02x}) at offset {position}",
                                   None)
            break
        if end > size:
            result.damage = _cut_record(file, opcode, position, size)
            break
        if opcode == Opcode.MESSAGE_INDEX and chunk is not None:
            if chunk.indexes is None:  # trusted: take the count and offset from the file's index
                channel_id, entries = struct.unpack("<HI", file.read(6))
                index = chunk.chunk_index
                assert index is not None
                index.message_index_offsets[channel_id] = position
                index.message_index_length = end - chunk.record_end
                chunk.counts[channel_id] = entries // 16
            chunk.end = position = end
            continue
        if chunk is not None:  # a record follows, so the chunk's indexes are all there
            result.units.append(chunk)
            chunk = None
        if opcode == Opcode.DATA_END:
            result.data_end = position
            break
        try:
            body = buffer.read(file, length)
            if opcode == Opcode.CHUNK:
                chunk = _chunk_unit(body, position, end)
                if check_chunks:
                    _read_chunk(file, chunk, result, check_chunks, _chunk_content(body, chunk))
            elif opcode == Opcode.MESSAGE_INDEX:
                raise InvalidRecord("message index without a chunk")
            else:
                result.units.append(_top_level_unit(opcode, body, position, end, result))
        except InvalidRecord as error:
            what = "damaged chunk" if opcode == Opcode.CHUNK else f"bad {_name(opcode)} record"
            result.damage = Damage(position, f"{what} at offset {position} ({error}): it and all after "
                                             f"it cut", None)
            return result
        position = end
    if chunk is not None and chunk.indexes is None:
        # Nothing whole follows the last chunk, so its indexes may be cut short: rebuild them.
        try:
            _read_chunk(file, chunk, result, check_chunks)
        except InvalidRecord as error:
            result.damage = Damage(chunk.start, f"{error} in the chunk at offset {chunk.start}: "
                                                f"1 chunk cut", None)
            chunk = None
    if chunk is not None:
        result.units.append(chunk)
    return result


def _cut_record(file: BinaryIO, opcode: int, position: int, size: int) -> Damage:
    """The damage of a record that the end of the file cuts short."""
    where = f"file ends inside a {_name(opcode)} record at offset {position}"
    if opcode == Opcode.CHUNK:
        lost = _partial_chunk_messages(file, position, size)
        count = f"at least {lost}" if lost else "an unknown number of"
        return Damage(position, f"{where}: 1 chunk ({count} messages) cut", lost)
    if opcode == Opcode.MESSAGE:
        return Damage(position, f"{where}: 1 message cut", 1)
    return Damage(position, where)


def _top_level_unit(opcode: int, body: bytes | memoryview, position: int, end: int, result: Scan) -> Unit:
    unit = Unit(position, end, end)
    if opcode == Opcode.SCHEMA:
        schema = _parse(Schema, body)
        assert isinstance(schema, Schema)
        result.schemas[schema.id] = schema
    elif opcode == Opcode.CHANNEL:
        channel = _parse(Channel, body)
        assert isinstance(channel, Channel)
        if channel.schema_id and channel.schema_id not in result.schemas:
            raise InvalidRecord(f"channel {channel.id} names unknown schema {channel.schema_id}")
        result.channels[channel.id] = channel
    elif opcode == Opcode.MESSAGE:
        if len(body) < 22:
            raise InvalidRecord("message record too short")
        channel_id, _sequence, log_time = struct.unpack_from("<HIQ", body)
        if channel_id not in result.channels:
            raise InvalidRecord(f"message on unknown channel {channel_id}")
        if result.units and (previous := result.units[-1]).chunk_index is None and previous.last_ns is not None \
                and log_time < previous.last_ns:
            # Readers accept unindexed messages only in log time order; out of order here is damage.
            raise InvalidRecord("log time going backwards in unindexed messages")
        unit.counts, unit.first_ns, unit.last_ns = {channel_id: 1}, log_time, log_time
    elif opcode == Opcode.METADATA:
        metadata = _parse(Metadata, body)
        assert isinstance(metadata, Metadata)
        result.metadata[metadata.name] = metadata.metadata
        unit.metadata_index = MetadataIndex(position, end - position, metadata.name)
    return unit


def _chunk_unit(body: bytes | memoryview, position: int, end: int) -> Unit:
    try:
        start_ns, end_ns, uncompressed_size, crc, name_length = struct.unpack_from("<QQQII", body)
        compression = bytes(body[32:32 + name_length]).decode()
        (compressed_size,) = struct.unpack_from("<Q", body, 32 + name_length)
    except (struct.error, UnicodeDecodeError) as error:
        raise InvalidRecord(f"unreadable chunk header ({error})") from error
    if 40 + name_length + compressed_size != len(body):
        raise InvalidRecord("chunk record of the wrong length")
    index = ChunkIndex(
        chunk_length=end - position, chunk_start_offset=position, compression=compression,
        compressed_size=compressed_size, message_end_time=end_ns, message_index_length=0,
        message_index_offsets={}, message_start_time=start_ns, uncompressed_size=uncompressed_size,
    )
    return Unit(position, end, end, crc=crc, first_ns=start_ns, last_ns=end_ns, chunk_index=index)


class _Buffer:
    """One reusable buffer for the records a scan reads: a chunk of camera frames is read into memory the
    process already has, not into a fresh allocation (page faults) per chunk."""

    def __init__(self) -> None:
        self._data = bytearray()

    def read(self, file: BinaryIO, length: int) -> memoryview:
        """The next ``length`` bytes of ``file`` (fewer at its end), valid until the next read."""
        if len(self._data) < length:
            self._data = bytearray(length)
        view = memoryview(self._data)[:length]
        got = file.readinto(view)  # type: ignore[attr-defined]
        return view[:got]


def _chunk_content(body: memoryview, chunk: Unit) -> memoryview:
    """The (compressed) records of a chunk record whose body (after opcode and length) is ``body``."""
    index = chunk.chunk_index
    assert index is not None
    start = 32 + len(index.compression.encode()) + 8
    return body[start:start + index.compressed_size]


def _read_chunk(file: BinaryIO, chunk: Unit, result: Scan, check_references: bool,
                content: bytes | memoryview | None = None) -> None:
    """Read the chunk's content: its counts, times and rebuilt message indexes; raises ``InvalidRecord``.

    ``check_references``: messages must name a channel defined before them (in this chunk or the
    records read before it); off when earlier chunks were not read. ``content``: the chunk's records as
    already read (else they are read from ``file``).
    """
    index = chunk.chunk_index
    assert index is not None
    if content is None:
        file.seek(chunk.start + 9 + 32 + len(index.compression.encode()) + 8)
        content = file.read(index.compressed_size)
    data = decompress(index.compression, content, index.uncompressed_size)
    if len(data) != index.uncompressed_size:
        raise InvalidRecord("chunk content of the wrong size")
    if chunk.crc and zlib.crc32(data) != chunk.crc:
        raise InvalidRecord("chunk CRC mismatch")
    entries, schemas, channels = _chunk_records(data, result, check_references,
                                                (index.message_start_time, index.message_end_time))
    result.schemas.update(schemas)
    result.channels.update(channels)
    builder = RecordBuilder()
    index.message_index_offsets = {}
    for channel_id, records in entries.items():
        index.message_index_offsets[channel_id] = chunk.record_end + builder.count
        MessageIndex(channel_id=channel_id, records=records).write(builder)
    chunk.indexes = builder.end()
    index.message_index_length = len(chunk.indexes)
    chunk.counts = {channel_id: len(records) for channel_id, records in entries.items()}
    times = [log_time for records in entries.values() for log_time, _ in records]
    chunk.first_ns, chunk.last_ns = (min(times), max(times)) if times else (None, None)


def _chunk_records(
    data: bytes | memoryview, result: Scan, check_references: bool, time_range: tuple[int, int]
) -> tuple[dict[int, list[tuple[int, int]]], dict[int, Schema], dict[int, Channel]]:
    """Message index entries per channel, and the schemas and channels, of a chunk's content.

    A message outside the chunk header's ``time_range`` is damage (writers set the range from the
    messages; readers may skip messages outside it).
    """
    entries: dict[int, list[tuple[int, int]]] = {}
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    offset = 0
    while offset < len(data):
        if offset + 9 > len(data):
            raise InvalidRecord("record header cut inside the chunk")
        opcode, length = _RECORD_START.unpack_from(data, offset)
        end = offset + 9 + length
        if end > len(data):
            raise InvalidRecord("record cut inside the chunk")
        body = data[offset + 9:end]
        if opcode == Opcode.MESSAGE:
            if length < 22:
                raise InvalidRecord("message record too short")
            channel_id, _sequence, log_time = struct.unpack_from("<HIQ", body)
            if check_references and channel_id not in channels and channel_id not in result.channels:
                raise InvalidRecord(f"message on unknown channel {channel_id}")
            if not time_range[0] <= log_time <= time_range[1]:
                raise InvalidRecord("message log time outside the chunk's range")
            entries.setdefault(channel_id, []).append((log_time, offset))
        elif opcode == Opcode.SCHEMA:
            schema = _parse(Schema, body)
            assert isinstance(schema, Schema)
            schemas[schema.id] = schema
        elif opcode == Opcode.CHANNEL:
            channel = _parse(Channel, body)
            assert isinstance(channel, Channel)
            known = channel.schema_id in schemas or channel.schema_id in result.schemas
            if check_references and channel.schema_id and not known:
                raise InvalidRecord(f"channel {channel.id} names unknown schema {channel.schema_id}")
            channels[channel.id] = channel
        else:
            raise InvalidRecord(f"{_name(opcode)} record inside the chunk")
        offset = end
    return entries, schemas, channels


def _partial_chunk_messages(file: BinaryIO, position: int, size: int) -> int | None:
    """How many whole messages the written part of the cut chunk at ``position`` holds (``None``
    when it cannot be read, e.g. a compressed frame cut before its first block ends)."""
    file.seek(position + 9)
    body = file.read(size - position - 9)
    try:
        name_length = struct.unpack_from("<I", body, 28)[0]
        compression = body[32:32 + name_length].decode()
        content = body[40 + name_length:]
        if compression == "zstd":
            content = zstandard.ZstdDecompressor().decompressobj().decompress(content)
        elif compression == "lz4":
            content = lz4.frame.LZ4FrameDecompressor().decompress(content)
        elif compression:
            return None
    except Exception:  # whatever survived of a compressed frame: its size is then unknown
        return None
    count = offset = 0
    while offset + 9 <= len(content):
        opcode, length = _RECORD_START.unpack_from(content, offset)
        offset += 9 + length
        count += opcode == Opcode.MESSAGE and offset <= len(content)
    return count


def decompress(compression: str, data: bytes | memoryview, size: int) -> bytes | memoryview:
    """A chunk's content; any failure (unknown compression, damaged frame) raises ``InvalidRecord``."""
    try:
        if compression == "":
            return data
        if compression == "zstd":
            return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        if compression == "lz4":
            return bytes(lz4.frame.decompress(data))
    except Exception as error:  # the decompressors raise several types on damaged frames
        raise InvalidRecord(f"cannot decompress: {error}") from error
    raise InvalidRecord(f"unknown chunk compression {compression!r}")


def summary_tail(
    position: int, schemas: Sequence[Schema], channels: Sequence[Channel], metadata: dict[str, str] | None,
    totals: Totals, chunk_indexes: list[ChunkIndex], metadata_indexes: list[MetadataIndex],
) -> bytes:
    """Closing metadata record (``{name: {key: value}}``), data end, summary, footer and magic for a
    file whose records end at ``position``."""
    data = RecordBuilder()
    metadata_indexes = list(metadata_indexes)
    for name, content in (metadata or {}).items():
        record_start = data.count
        Metadata(name=name, metadata=content).write(data)
        metadata_indexes.append(MetadataIndex(position + record_start, data.count - record_start, name))
    DataEnd(0).write(data)
    summary_start = position + data.count
    summary = RecordBuilder()
    offsets: list[SummaryOffset] = []

    def group(opcode: Opcode, records: Sequence[McapRecord]) -> None:
        begin = summary.count
        for record in records:
            record.write(summary)
        offsets.append(SummaryOffset(opcode, summary_start + begin, summary.count - begin))

    group(Opcode.SCHEMA, schemas)
    group(Opcode.CHANNEL, channels)
    group(Opcode.STATISTICS, [Statistics(
        attachment_count=0, channel_count=len(channels), channel_message_counts=totals.counts,
        chunk_count=len(chunk_indexes), message_count=sum(totals.counts.values()),
        message_end_time=totals.last_ns or 0, message_start_time=totals.first_ns or 0,
        metadata_count=len(metadata_indexes), schema_count=len(schemas),
    )])
    group(Opcode.CHUNK_INDEX, chunk_indexes)
    group(Opcode.METADATA_INDEX, metadata_indexes)
    summary_offset_start = summary_start + summary.count
    for offset in offsets:
        offset.write(summary)
    summary_bytes = summary.end()
    crc = zlib.crc32(summary_bytes)
    crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc)
    footer = RecordBuilder()
    Footer(summary_start, summary_offset_start, crc).write(footer)
    return data.end() + summary_bytes + footer.end() + MAGIC
