"""One ``.mcap`` storage file laid out as rosbag2_storage_mcap writes it.

Records go through ``mcap.writer.Writer`` (profile ``ros2``; schemas ``ros2msg``/``ros2idl``;
channels with ``offered_qos_profiles`` and ``topic_type_hash`` metadata; a ``rosbag2`` metadata
record at open and at close; a full summary with statistics, chunk and message indexes).

An MCAP file without its summary cannot be opened by ``rosbags`` (ros2/rosbag2#1079, #2003), and
the disk filling up is exactly when the summary fails to be written. So when a write fails, this
storage repairs the file on close instead: it cuts the file after the last complete record (which
also frees the space the failed chunk took), rebuilds the message indexes of the last chunk and
appends a fresh summary, dropping trailing records only if even that does not fit.
"""
from __future__ import annotations

import contextlib
import io
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import lz4.frame
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from .metadata import ROS_DISTRO, FileInfo, TopicInfo, serialize_qos_profiles

__all__ = ["DEFAULT_CHUNK_SIZE", "LIBRARY", "MCAP_PRESETS", "McapStorage"]

#: rosbag2_storage_mcap's (libmcap's) default chunk size.
DEFAULT_CHUNK_SIZE = 786_432
LIBRARY = f"{LIBRARY_IDENTIFIER}; rosbag2_storage_mcap layout ({ROS_DISTRO})"
PROFILE = "ros2"
_METADATA_NAME = "rosbag2"
_METADATA_KEY = "serialized_metadata"
_MAGIC = b"\x89MCAP0\r\n"
# Unchunked files (fastwrite) get one record per message, batched by this buffer; chunked files
# are written a chunk at a time anyway, and a small buffer keeps what a failure can lose small.
_UNCHUNKED_BUFFER = 1 << 20
# How often a repair may shorten the file further when the summary does not fit.
_REPAIR_ATTEMPTS = 32


@dataclass(frozen=True)
class _Options:
    chunk_size: int = DEFAULT_CHUNK_SIZE
    compression: CompressionType = CompressionType.NONE
    use_chunking: bool = True


#: rosbag2's storage presets. The Python writer cannot choose a zstd level, so both zstd presets
#: use zstd's default level; ``zstd_small`` keeps rosbag2's larger (better compressing) chunks.
#: ``fastwrite`` writes no chunks and so no message indexes, but still a summary.
MCAP_PRESETS: dict[str, _Options] = {
    "": _Options(),
    "none": _Options(),
    "fastwrite": _Options(use_chunking=False),
    "zstd_fast": _Options(compression=CompressionType.ZSTD),
    "zstd_small": _Options(chunk_size=4 * 1024 * 1024, compression=CompressionType.ZSTD),
}


class McapStorage:
    """Writes one MCAP file; single-threaded (the bag writer serializes access).

    ``data`` of :meth:`write` may be ``bytes``, ``bytearray`` or ``memoryview``: it is copied once,
    into the chunk (or record) buffer, and not referenced afterwards.
    """

    storage_id = "mcap"
    extension = ".mcap"
    presets = MCAP_PRESETS

    def __init__(self, path: Path, preset: str = "", serialized_metadata: str = "") -> None:
        """Create ``path`` (never overwriting it) and write the header and opening metadata."""
        if preset not in MCAP_PRESETS:
            raise ValueError(
                f"unknown MCAP storage preset profile {preset!r} "
                f"(valid: {', '.join(repr(name) for name in MCAP_PRESETS)})"
            )
        options = MCAP_PRESETS[preset]
        self.path = path
        #: The first write error; after it the file only gets repaired and closed.
        self.error: OSError | None = None
        #: False only if the file could not be given a summary (then readers cannot open it).
        self.readable = True
        buffering = io.DEFAULT_BUFFER_SIZE if options.use_chunking else _UNCHUNKED_BUFFER
        self._file: BinaryIO = open(path, "xb", buffering=buffering)  # noqa: SIM115
        self._writer = Writer(
            self._file,
            chunk_size=options.chunk_size,
            compression=options.compression,
            use_chunking=options.use_chunking,
            # rosbag2 skips chunk CRCs (a tenth of the write time for large images); the Python
            # writer can only switch all CRCs together.
            enable_crcs=False,
        )
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        self._topics_by_channel: dict[int, str] = {}
        self._sequences: dict[int, int] = {}
        # Copies of the registered records: a repair writes them into the new summary.
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._counts: dict[str, int] = {}
        self._first_ns: int | None = None
        self._last_ns: int | None = None
        # Bytes of messages held in the unfinished chunk (not yet in the file).
        self._pending = 0
        self._info: FileInfo | None = None
        try:
            self._writer.start(profile=PROFILE, library=LIBRARY)
            if serialized_metadata:
                self._writer.add_metadata(_METADATA_NAME, {_METADATA_KEY: serialized_metadata})
        except OSError as error:
            self._fail(error)
            raise

    @property
    def size(self) -> int:
        """Bytes in the file plus the unfinished chunk: what the file will hold once it is flushed."""
        return self._file.tell() + self._pending if not self._file.closed else self.path.stat().st_size

    def add_topic(self, topic: TopicInfo, definition: tuple[str, str]) -> None:
        """Register the topic's channel, and its type's schema once, with rosbag2's metadata.

        ``definition`` is ``(encoding, text)`` from :func:`.message_definitions.message_definition`.
        """
        self._require_open()
        if topic.name in self._channel_ids:
            return
        try:
            schema_id = self._schema_ids.get(topic.type)
            if schema_id is None:
                encoding, text = definition
                data = text.encode()
                schema_id = self._writer.register_schema(topic.type, encoding, data)
                self._schema_ids[topic.type] = schema_id
                self._schemas.append(Schema(id=schema_id, data=data, encoding=encoding, name=topic.type))
            metadata = {
                "offered_qos_profiles": serialize_qos_profiles(topic.offered_qos_profiles),
                "topic_type_hash": topic.type_description_hash,
            }
            channel_id = self._writer.register_channel(
                topic.name, topic.serialization_format, schema_id, metadata
            )
        except OSError as error:
            self._fail(error)
            raise
        self._channels.append(Channel(
            id=channel_id, topic=topic.name, message_encoding=topic.serialization_format,
            schema_id=schema_id, metadata=metadata,
        ))
        self._channel_ids[topic.name] = channel_id
        self._topics_by_channel[channel_id] = topic.name
        self._sequences[channel_id] = 0
        self._counts[topic.name] = 0

    def write(
        self, topic: str, data: bytes | bytearray | memoryview, log_time_ns: int, publish_time_ns: int
    ) -> None:
        """Append one message; raises ``OSError`` when the file cannot grow (see :meth:`close`)."""
        self._require_open()
        channel_id = self._channel_ids[topic]
        sequence = self._sequences[channel_id]
        position = self._file.tell()
        try:
            self._writer.add_message(
                channel_id=channel_id, log_time=log_time_ns, data=data,  # type: ignore[arg-type]
                publish_time=publish_time_ns, sequence=sequence,
            )
        except OSError as error:
            self._fail(error)
            raise
        self._sequences[channel_id] = (sequence + 1) & 0xFFFFFFFF
        self._counts[topic] += 1
        if self._first_ns is None or log_time_ns < self._first_ns:
            self._first_ns = log_time_ns
        if self._last_ns is None or log_time_ns > self._last_ns:
            self._last_ns = log_time_ns
        # A chunk (with this message in it) went to the file, or the message is still buffered.
        self._pending = 0 if self._file.tell() != position else self._pending + len(data) + 31

    def close(self, serialized_metadata: str = "") -> FileInfo:
        """Finish the file (closing metadata record, summary, footer) and describe what it holds.

        Never raises for I/O errors: after one (here or in an earlier call) the file is repaired to
        hold every complete record and the returned counts cover exactly those; :attr:`error` tells
        what went wrong and :attr:`readable` whether the repair succeeded.
        """
        if self._info is not None:
            return self._info
        if self.error is None:
            try:
                if serialized_metadata:
                    self._writer.add_metadata(_METADATA_NAME, {_METADATA_KEY: serialized_metadata})
                self._writer.finish()
                self._file.close()
            except OSError as error:
                self._fail(error)
        if self.error is None:
            self._info = FileInfo.from_log_times(self.path.name, self._first_ns, self._last_ns, self._counts)
        else:
            self._info = self._repair(serialized_metadata)
        return self._info

    def _require_open(self) -> None:
        if self._info is not None:
            raise ValueError(f"{self.path} is closed")
        if self.error is not None:
            raise OSError(self.error.errno, f"earlier write failed: {self.error.strerror}", str(self.path))

    def _fail(self, error: OSError) -> None:
        if self.error is None:
            self.error = error
        try:
            with contextlib.suppress(OSError):
                self._file.close()  # flushing the buffer fails again; the repair reads the file
        finally:
            raw = getattr(self._file, "raw", None)
            if raw is not None and not raw.closed:
                raw.close()

    def _repair(self, serialized_metadata: str) -> FileInfo:
        result = _repair_file(self.path, self._schemas, self._channels, serialized_metadata)
        self.readable = result is not None
        if result is None:
            return FileInfo(self.path.name)
        counts = {self._topics_by_channel[channel]: count for channel, count in result.counts.items()}
        return FileInfo.from_log_times(self.path.name, result.first_ns, result.last_ns, counts)


# --- repair after a failed write -------------------------------------------------------------


@dataclass
class _Unit:
    """A complete top-level record (a chunk counts with its message indexes) found in the file."""

    end: int
    rewrite: bytes = b""  # appended at ``end - len(rewrite)``: rebuilt indexes of the last chunk
    counts: dict[int, int] = field(default_factory=dict)
    first_ns: int | None = None
    last_ns: int | None = None
    chunk_index: ChunkIndex | None = None
    metadata_index: MetadataIndex | None = None


@dataclass
class _RepairResult:
    counts: dict[int, int]
    first_ns: int | None
    last_ns: int | None


def _repair_file(
    path: Path, schemas: list[Schema], channels: list[Channel], serialized_metadata: str
) -> _RepairResult | None:
    """Cut ``path`` after its last complete record and append a summary; ``None`` if impossible."""
    try:
        # Unbuffered, so a failed write leaves nothing behind that a later flush could append.
        with open(path, "r+b", buffering=0) as file:
            start, units = _scan(file, file.seek(0, io.SEEK_END))
            keep = len(units)
            metadata = serialized_metadata
            for _ in range(_REPAIR_ATTEMPTS):
                kept = units[:keep]
                if not start:  # not even the header made it: begin the file anew
                    base, head = 0, _MAGIC + _header_record()
                elif kept:
                    base, head = kept[-1].end - len(kept[-1].rewrite), kept[-1].rewrite
                else:
                    base, head = start, b""
                tail = head + _tail(kept, base + len(head), schemas, channels, metadata)
                try:
                    file.truncate(base)
                    file.seek(base)
                    _write_all(file, tail)
                    return _summarize(kept)
                except OSError:
                    file.truncate(base)
                # Out of space: drop the closing metadata record first, then trailing records
                # until the summary's size has been freed.
                if metadata:
                    metadata = ""
                    continue
                if not kept:
                    return None
                while keep and units[keep - 1].end > base - len(tail):
                    keep -= 1
    except OSError:
        return None
    return None


def _write_all(file: BinaryIO, data: bytes) -> None:
    view = memoryview(data)
    while view:
        written = file.write(view)
        if not written:
            raise OSError(f"short write to {file.name}")
        view = view[written:]


def _header_record() -> bytes:
    builder = RecordBuilder()
    Header(PROFILE, LIBRARY).write(builder)
    return builder.end()


def _read_record_start(file: BinaryIO, position: int, size: int) -> tuple[int, int] | None:
    """Opcode and end offset of the record at ``position``, or ``None`` if it is incomplete."""
    if position + 9 > size:
        return None
    file.seek(position)
    opcode, length = struct.unpack("<BQ", file.read(9))
    end = position + 9 + length
    return (opcode, end) if end <= size else None


def _scan(file: BinaryIO, size: int) -> tuple[int, list[_Unit]]:
    """Offset where records begin (0 if even the header is incomplete) and the complete units."""
    file.seek(0)
    if file.read(8) != _MAGIC:
        return 0, []
    header = _read_record_start(file, 8, size)
    if header is None or header[0] != Opcode.HEADER:
        return 0, []
    start = position = header[1]
    units: list[_Unit] = []
    chunk: _Unit | None = None  # the latest chunk, while its message indexes are read
    while (record := _read_record_start(file, position, size)) is not None:
        opcode, end = record
        body = end - position - 9
        if opcode == Opcode.MESSAGE_INDEX and chunk is not None:
            channel_id, length = struct.unpack("<HI", file.read(6))
            index = chunk.chunk_index
            assert index is not None
            index.message_index_offsets[channel_id] = position
            index.message_index_length = end - index.chunk_start_offset - index.chunk_length
            chunk.counts[channel_id] = length // 16
            chunk.end = end
            position = end
            continue
        if chunk is not None:  # a record follows, so the chunk's indexes are all there
            units.append(chunk)
            chunk = None
        if opcode == Opcode.DATA_END:
            break
        if opcode == Opcode.CHUNK:
            chunk = _chunk_unit(file, position, end)
        elif opcode == Opcode.MESSAGE:
            channel_id, _sequence, log_time = struct.unpack("<HIQ", file.read(14))
            units.append(_Unit(end, counts={channel_id: 1}, first_ns=log_time, last_ns=log_time))
        elif opcode == Opcode.METADATA:
            (name_length,) = struct.unpack("<I", file.read(4))
            name = file.read(name_length).decode()
            units.append(_Unit(end, metadata_index=MetadataIndex(position, body + 9, name)))
        else:
            units.append(_Unit(end))
        position = end
    if chunk is not None:
        # Nothing follows the last chunk, so its indexes may be cut short: rebuild them.
        rebuilt = _rebuild_indexes(file, chunk)
        if rebuilt is not None:
            units.append(rebuilt)
    return start, units


def _chunk_unit(file: BinaryIO, position: int, end: int) -> _Unit:
    start_ns, end_ns, uncompressed_size, _crc, name_length = struct.unpack("<QQQII", file.read(32))
    compression = file.read(name_length).decode()
    (compressed_size,) = struct.unpack("<Q", file.read(8))
    index = ChunkIndex(
        chunk_length=end - position, chunk_start_offset=position, compression=compression,
        compressed_size=compressed_size, message_end_time=end_ns, message_index_length=0,
        message_index_offsets={}, message_start_time=start_ns, uncompressed_size=uncompressed_size,
    )
    return _Unit(end, first_ns=start_ns, last_ns=end_ns, chunk_index=index)


def _rebuild_indexes(file: BinaryIO, chunk: _Unit) -> _Unit | None:
    """The chunk with message indexes recomputed from its content; ``None`` if it is unreadable."""
    index = chunk.chunk_index
    assert index is not None
    header_length = 9 + 32 + len(index.compression.encode()) + 8
    file.seek(index.chunk_start_offset + header_length)
    try:
        data = _decompress(index.compression, file.read(index.compressed_size), index.uncompressed_size)
    except (RuntimeError, ValueError, zstandard.ZstdError):
        return None
    entries: dict[int, list[tuple[int, int]]] = {}
    offset = 0
    while offset + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, offset)
        if opcode == Opcode.MESSAGE:
            channel_id, _sequence, log_time = struct.unpack_from("<HIQ", data, offset + 9)
            entries.setdefault(channel_id, []).append((log_time, offset))
        offset += 9 + length
    chunk_end = index.chunk_start_offset + index.chunk_length
    builder = RecordBuilder()
    index.message_index_offsets = {}
    for channel_id, records in entries.items():
        index.message_index_offsets[channel_id] = chunk_end + builder.count
        MessageIndex(channel_id=channel_id, records=records).write(builder)
    rewrite = builder.end()
    index.message_index_length = len(rewrite)
    counts = {channel_id: len(records) for channel_id, records in entries.items()}
    return _Unit(chunk_end + len(rewrite), rewrite, counts, chunk.first_ns, chunk.last_ns, index)


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        return bytes(lz4.frame.decompress(data))
    raise ValueError(f"unknown chunk compression {compression!r}")


def _summarize(units: list[_Unit]) -> _RepairResult:
    counts: dict[int, int] = {}
    first: int | None = None
    last: int | None = None
    for unit in units:
        for channel_id, count in unit.counts.items():
            counts[channel_id] = counts.get(channel_id, 0) + count
        if unit.counts and unit.first_ns is not None and unit.last_ns is not None:
            first = unit.first_ns if first is None else min(first, unit.first_ns)
            last = unit.last_ns if last is None else max(last, unit.last_ns)
    return _RepairResult(counts, first, last)


def _tail(
    units: list[_Unit], position: int, schemas: list[Schema], channels: list[Channel], metadata: str
) -> bytes:
    """Closing metadata, data end, summary, footer and magic for a file cut at ``position``."""
    data = RecordBuilder()
    metadata_indexes = [unit.metadata_index for unit in units if unit.metadata_index is not None]
    if metadata:
        record = Metadata(name=_METADATA_NAME, metadata={_METADATA_KEY: metadata})
        record.write(data)
        metadata_indexes.append(MetadataIndex(position, data.count, _METADATA_NAME))
    DataEnd(0).write(data)
    summary_start = position + data.count
    summary = RecordBuilder()
    offsets: list[SummaryOffset] = []

    def group(opcode: Opcode, records: Sequence[McapRecord]) -> None:
        begin = summary.count
        for record in records:
            record.write(summary)
        offsets.append(SummaryOffset(opcode, summary_start + begin, summary.count - begin))

    result = _summarize(units)
    chunk_indexes = [unit.chunk_index for unit in units if unit.chunk_index is not None]
    group(Opcode.SCHEMA, schemas)
    group(Opcode.CHANNEL, channels)
    group(Opcode.STATISTICS, [Statistics(
        attachment_count=0, channel_count=len(channels), channel_message_counts=result.counts,
        chunk_count=len(chunk_indexes), message_count=sum(result.counts.values()),
        message_end_time=result.last_ns or 0, message_start_time=result.first_ns or 0,
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
    return data.end() + summary_bytes + footer.end() + _MAGIC
