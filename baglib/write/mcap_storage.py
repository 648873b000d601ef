"""One ``.mcap`` storage file laid out as rosbag2_storage_mcap writes it.

Profile ``ros2``; schemas ``ros2msg``/``ros2idl``; channels with ``offered_qos_profiles`` and
``topic_type_hash`` metadata; a ``rosbag2`` metadata record at open and at close; chunks (holding the
schema and channel records registered since the previous chunk, then the messages) each followed by
its message indexes; a full summary with schemas, channels, statistics, chunk and metadata indexes.

The records are built here rather than by ``mcap.writer.Writer`` because that writer copies every
message three times before the kernel does (into the chunk's ``BytesIO``, out of it, into the chunk
record's ``BytesIO``), which made the recorder drop camera frames. Here a chunk is a list of buffers:
small records are copied once into a ``bytearray``, and a big message whose arrival completes the
chunk is written straight from the caller's buffers (a ``memoryview`` of the image's pixels from
:mod:`.cdr_fast`), so its payload is not copied before the kernel gets it (and with direct I/O not
even by the kernel, see below). The layout, indexes and summary are the same as the Python writer's.
Chunk CRCs stay zero, as ``enable_crcs=False`` wrote them (and rosbag2's ``fastwrite``/``zstd_fast``
presets): zlib's crc32 of one 1080p frame takes longer than writing the frame.

An MCAP file without its summary cannot be opened by ``rosbags`` (ros2/rosbag2#1079, #2003), and
the disk filling up is exactly when the summary fails to be written. So when a write fails, this
storage repairs the file on close instead: it cuts the file after the last complete record (which
also frees the space the failed chunk took), rebuilds the message indexes of the last chunk and
appends a fresh summary, dropping trailing records only if even that does not fit. Finding the
complete records is :mod:`.mcap_records`, shared with ``bag recover``.

On a direct-I/O file a big message's payload is written from the caller's memory only when memory and file
agree on its offset within a disk block (:mod:`.direct_file`). To get there, the chunk (or, unchunked, the
message record) is preceded by a padding record of up to 4.1 KiB (:data:`PADDING_OPCODE`, a private opcode of
the 0x80-0xFF range the MCAP specification reserves for extensions): every MCAP reader skips records it does
not know, and indexed readers never see it (chunk indexes point past it). At most 0.07 % of a 1080p frame.
"""
from __future__ import annotations

import contextlib
import os
import io
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Protocol

import lz4.frame
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Header, McapRecord, Metadata, MetadataIndex, Schema
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType

from baglib.write.direct_file import BLOCK, DirectFile, open_exclusive

from baglib.format.mcap_records import MAGIC, Totals, scan, summary_tail
from baglib.format.durable import fsync_directory
from baglib.format.metadata import ROS_DISTRO, FileInfo, TopicInfo, serialize_qos_profiles

__all__ = ["DEFAULT_CHUNK_SIZE", "LIBRARY", "MCAP_PRESETS", "METADATA_KEY", "METADATA_NAME", "PADDING_OPCODE",
           "McapStorage", "MessageBuffers"]

#: rosbag2_storage_mcap's (libmcap's) default chunk size.
DEFAULT_CHUNK_SIZE = 786_432
LIBRARY = f"{LIBRARY_IDENTIFIER}; rosbag2_storage_mcap layout ({ROS_DISTRO})"
PROFILE = "ros2"
METADATA_NAME = "rosbag2"
METADATA_KEY = "serialized_metadata"
# Unchunked files (fastwrite) get one record per message, batched by this buffer; chunked files
# are written a chunk at a time anyway, and a small buffer keeps what a failure can lose small.
_UNCHUNKED_BUFFER = 1 << 20
# How often a repair may shorten the file further when the summary does not fit.
_REPAIR_ATTEMPTS = 32
# A buffer of a chunk-completing message at least this big is written from where it is, not copied.
_WRITE_IN_PLACE = 64 * 1024

# opcode, record length, channel id, sequence, log time, publish time: the 31 bytes before the data
_MESSAGE_HEADER = struct.Struct("<BQHIQQ")
_MESSAGE_HEADER_FIELDS = 22
# opcode, record length, start, end, uncompressed size, uncompressed CRC, compression name length
_CHUNK_HEADER = struct.Struct("<BQQQQII")
_U64 = struct.Struct("<Q")
#: The opcode of the padding records (zeros) that align big payloads for direct I/O (module docstring).
PADDING_OPCODE = 0x80
# opcode and record length: the smallest record, and so the smallest padding
_RECORD_START = struct.Struct("<BQ")
# opcode, record length, channel id, byte length of the (log time, offset) entries that follow
_MESSAGE_INDEX_HEADER = struct.Struct("<BQHI")
_INDEX_ENTRY = struct.Struct("<QQ")
_COMPRESSION_NAMES = {CompressionType.NONE: "", CompressionType.LZ4: "lz4", CompressionType.ZSTD: "zstd"}

_Buffer = bytes | bytearray | memoryview


class MessageBuffers(Protocol):
    """A serialized message in consecutive pieces (:class:`.cdr_fast.SerializedBuffers`)."""

    buffers: tuple[_Buffer, ...]

    def __len__(self) -> int: ...


@dataclass(frozen=True)
class _Options:
    chunk_size: int = DEFAULT_CHUNK_SIZE
    compression: CompressionType = CompressionType.NONE
    use_chunking: bool = True


#: rosbag2's storage presets. Both zstd presets use zstd's default level (3) as the Python writer
#: did; ``zstd_small`` keeps rosbag2's larger (better compressing) chunks.
#: ``fastwrite`` writes no chunks and so no message indexes, but still a summary.
MCAP_PRESETS: dict[str, _Options] = {
    "": _Options(),
    "none": _Options(),
    "fastwrite": _Options(use_chunking=False),
    "zstd_fast": _Options(compression=CompressionType.ZSTD),
    "zstd_small": _Options(chunk_size=4 * 1024 * 1024, compression=CompressionType.ZSTD),
}


def _nbytes(buffer: _Buffer) -> int:
    return buffer.nbytes if isinstance(buffer, memoryview) else len(buffer)


def _record(record: McapRecord) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


class McapStorage:
    """Writes one MCAP file; single-threaded (the bag writer serializes access).

    ``data`` of :meth:`write` may be ``bytes``, ``bytearray``, ``memoryview`` or
    :class:`MessageBuffers`. Small data is copied into the open chunk; a big buffer that completes a chunk is
    written from where it is before :meth:`write` returns, unless the storage gathers writes (``gather_bytes``,
    direct I/O): then it must not change until :meth:`flush` or :meth:`close` returns (see :mod:`.direct_file`).
    """

    storage_id = "mcap"
    extension = ".mcap"
    presets = MCAP_PRESETS

    def __init__(self, path: Path, preset: str = "", serialized_metadata: str = "", gather_bytes: int = 0) -> None:
        """Create ``path`` (never overwriting it) and write the header and opening metadata; with direct I/O,
        gather up to ``gather_bytes`` of whole blocks into one write (see the class docstring)."""
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
        self._chunked = options.use_chunking
        self._chunk_size = options.chunk_size
        self._compression = _COMPRESSION_NAMES[options.compression]
        buffering = io.DEFAULT_BUFFER_SIZE if options.use_chunking else _UNCHUNKED_BUFFER
        self._file: BinaryIO | DirectFile = open_exclusive(path, buffering, gather_bytes)
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        self._topics_by_channel: dict[int, str] = {}
        self._sequences: dict[int, int] = {}
        # The registered records, repeated in the summary (also by a repair).
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._counts: dict[str, int] = {}
        self._first_ns: int | None = None
        self._last_ns: int | None = None
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        # The open chunk: written parts, the records being copied, its uncompressed length, the
        # message index entries per channel and the time range of its messages.
        self._chunk_parts: list[_Buffer] = []
        self._chunk_largest: _Buffer | None = None  # the largest of the caller's buffers among the parts
        self._chunk_records = bytearray()
        self._chunk_length = 0
        self._chunk_entries: dict[int, bytearray] = {}
        self._chunk_messages = 0
        self._chunk_start_ns = 0
        self._chunk_end_ns = 0
        self._info: FileInfo | None = None
        try:
            self._file.write(MAGIC)
            self._file.write(_header_record())
            if serialized_metadata:
                self._write_metadata(serialized_metadata)
        except OSError as error:
            self._fail(error)
            raise

    @property
    def size(self) -> int:
        """Bytes in the file plus the unfinished chunk: what the file will hold once it is flushed."""
        return self._file.tell() + self._chunk_length if not self._file.closed else self.path.stat().st_size

    def add_topic(self, topic: TopicInfo, definition: tuple[str, str]) -> None:
        """Register the topic's channel, and its type's schema once, with rosbag2's metadata.

        ``definition`` is ``(encoding, text)`` from :func:`.message_definitions.message_definition`.
        In a chunked file the records go into the open chunk (as libmcap and the Python writer do).
        """
        self._require_open()
        if topic.name in self._channel_ids:
            return
        records = b""
        schema_id = self._schema_ids.get(topic.type)
        schema: Schema | None = None
        if schema_id is None:
            encoding, text = definition
            schema_id = len(self._schemas) + 1
            schema = Schema(id=schema_id, data=text.encode(), encoding=encoding, name=topic.type)
            records += _record(schema)
        metadata = {
            "offered_qos_profiles": serialize_qos_profiles(topic.offered_qos_profiles),
            "topic_type_hash": topic.type_description_hash,
        }
        channel_id = len(self._channels) + 1
        channel = Channel(id=channel_id, topic=topic.name, message_encoding=topic.serialization_format,
                          schema_id=schema_id, metadata=metadata)
        records += _record(channel)
        if self._chunked:
            self._chunk_records += records
            self._chunk_length += len(records)
        else:
            try:
                self._file.write(records)
            except OSError as error:
                self._fail(error)
                raise
        if schema is not None:
            self._schema_ids[topic.type] = schema_id
            self._schemas.append(schema)
        self._channels.append(channel)
        self._channel_ids[topic.name] = channel_id
        self._topics_by_channel[channel_id] = topic.name
        self._sequences[channel_id] = 0
        self._counts[topic.name] = 0

    def write(
        self, topic: str, data: bytes | bytearray | memoryview | MessageBuffers, log_time_ns: int,
        publish_time_ns: int,
    ) -> None:
        """Append one message; raises ``OSError`` when the file cannot grow (see :meth:`close`)."""
        self._require_open()
        channel_id = self._channel_ids[topic]
        sequence = self._sequences[channel_id]
        parts: tuple[_Buffer, ...]
        if isinstance(data, (bytes, bytearray, memoryview)):
            parts = (data,)
        else:  # MessageBuffers, or any other object with the buffer protocol (array, numpy)
            buffers = getattr(data, "buffers", None)
            parts = tuple(buffers) if buffers is not None else (memoryview(data),)
        size = sum(_nbytes(part) for part in parts)
        header = _MESSAGE_HEADER.pack(Opcode.MESSAGE, _MESSAGE_HEADER_FIELDS + size, channel_id, sequence,
                                      log_time_ns, publish_time_ns)
        try:
            if self._chunked:
                self._add_to_chunk(channel_id, log_time_ns, header, parts, size)
            else:
                self._pad(len(header), parts, max(parts, key=_nbytes))
                self._file.write(header)
                for part in parts:
                    self._file.write(part)
        except OSError as error:
            self._fail(error)
            raise
        self._sequences[channel_id] = (sequence + 1) & 0xFFFFFFFF
        self._counts[topic] += 1
        if self._first_ns is None or log_time_ns < self._first_ns:
            self._first_ns = log_time_ns
        if self._last_ns is None or log_time_ns > self._last_ns:
            self._last_ns = log_time_ns

    def flush(self) -> None:
        """Close the open chunk and hand every byte written so far to the OS: from now on a crash of the
        process cannot lose or cut a message written before this call (a power loss can, until an fsync).
        """
        self._require_open()
        try:
            self._finish_chunk()
            if isinstance(self._file, DirectFile):
                self._file.write_through()
            else:
                self._file.flush()
        except OSError as error:
            self._fail(error)
            raise

    def write_gathered(self) -> None:
        """Start writing what the file has gathered (direct I/O; a buffered file writes its buffer when it is
        full): the writer calls this when it has no more messages at hand. The open chunk stays open."""
        self._require_open()
        if isinstance(self._file, DirectFile):
            try:
                self._file.write_gathered()
            except OSError as error:
                self._fail(error)
                raise

    def close(self, serialized_metadata: str = "") -> FileInfo:
        """Finish the file (last chunk, closing metadata record, summary, footer), fsync it and describe it.

        Never raises for I/O errors: after one (here or in an earlier call) the file is repaired to
        hold every complete record and the returned counts cover exactly those; :attr:`error` tells
        what went wrong and :attr:`readable` whether the repair succeeded.
        """
        if self._info is not None:
            return self._info
        if self.error is None:
            try:
                self._finish_chunk()
                counts = {self._channel_ids[topic]: count for topic, count in self._counts.items() if count}
                self._file.write(summary_tail(
                    self._file.tell(), self._schemas, self._channels,
                    {METADATA_NAME: {METADATA_KEY: serialized_metadata}} if serialized_metadata else None,
                    Totals(counts, self._first_ns, self._last_ns), self._chunk_indexes, self._metadata_indexes,
                ))
                _close_synced(self._file, self.path.parent)  # before metadata.yaml can name this file
            except OSError as error:
                self._fail(error)
        if self.error is None:
            self._info = FileInfo.from_log_times(self.path.name, self._first_ns, self._last_ns, self._counts)
        else:
            self._info = self._repair(serialized_metadata)
        return self._info

    # --- records ----------------------------------------------------------------------------------

    def _write_metadata(self, serialized_metadata: str) -> None:
        record = _record(Metadata(name=METADATA_NAME, metadata={METADATA_KEY: serialized_metadata}))
        self._metadata_indexes.append(MetadataIndex(self._file.tell(), len(record), METADATA_NAME))
        self._file.write(record)

    def _add_to_chunk(
        self, channel_id: int, log_time_ns: int, header: bytes, parts: tuple[_Buffer, ...], size: int
    ) -> None:
        """Put one message into the open chunk, and write the chunk if it is now full.

        Until the chunk is written its content is copied (the caller's buffers may change after
        :meth:`write`); a message that fills the chunk is written from the caller's buffers.
        """
        if self._chunk_messages == 0:
            self._chunk_start_ns = self._chunk_end_ns = log_time_ns
        else:
            self._chunk_start_ns = min(self._chunk_start_ns, log_time_ns)
            self._chunk_end_ns = max(self._chunk_end_ns, log_time_ns)
        entries = self._chunk_entries.get(channel_id)
        if entries is None:
            entries = self._chunk_entries[channel_id] = bytearray()
        entries += _INDEX_ENTRY.pack(log_time_ns, self._chunk_length)
        self._chunk_messages += 1
        self._chunk_length += len(header) + size
        records = self._chunk_records
        records += header
        if self._chunk_length <= self._chunk_size:
            for part in parts:
                records += part
            return
        for part in parts:
            if _nbytes(part) < _WRITE_IN_PLACE:
                records += part
            else:
                self._chunk_parts += (records, part)
                records = self._chunk_records = bytearray()
                if self._chunk_largest is None or _nbytes(part) > _nbytes(self._chunk_largest):
                    self._chunk_largest = part
        self._finish_chunk()

    def _finish_chunk(self) -> None:
        """Write the open chunk (if it holds a message) and its message indexes; forget it."""
        if self._chunk_messages == 0:
            return
        try:
            parts = self._chunk_parts
            if self._chunk_records:
                parts.append(self._chunk_records)
            length = self._chunk_length
            compression = self._compression
            if compression:
                parts = [_compress(compression, parts, length)]
            compressed_size = sum(_nbytes(part) for part in parts)
            name = compression.encode()
            head = _CHUNK_HEADER.pack(
                Opcode.CHUNK, 8 + 8 + 8 + 4 + 4 + len(name) + 8 + compressed_size,
                self._chunk_start_ns, self._chunk_end_ns, length, 0, len(name),
            ) + name + _U64.pack(compressed_size)
            if not compression and self._chunk_largest is not None:
                self._pad(len(head), parts, self._chunk_largest)
            start = self._file.tell()
            self._file.write(head)
            for part in parts:
                self._file.write(part)
            indexes = bytearray()
            offsets: dict[int, int] = {}
            index_start = start + len(head) + compressed_size
            for channel_id, entries in self._chunk_entries.items():
                offsets[channel_id] = index_start + len(indexes)
                indexes += _MESSAGE_INDEX_HEADER.pack(Opcode.MESSAGE_INDEX, 6 + len(entries), channel_id,
                                                      len(entries))
                indexes += entries
            self._file.write(indexes)
            self._file.flush()  # a chunk is the unit a failure may lose: hand it to the OS now
            self._chunk_indexes.append(ChunkIndex(
                message_start_time=self._chunk_start_ns, message_end_time=self._chunk_end_ns,
                chunk_start_offset=start, chunk_length=len(head) + compressed_size,
                message_index_offsets=offsets, message_index_length=len(indexes), compression=compression,
                compressed_size=compressed_size, uncompressed_size=length,
            ))
        finally:  # also after a failure: the parts may reference the caller's buffers
            self._chunk_parts = []
            self._chunk_largest = None
            self._chunk_records = bytearray()
            self._chunk_length = 0
            self._chunk_entries = {}
            self._chunk_messages = 0

    def _pad(self, ahead: int, parts: list[_Buffer] | tuple[_Buffer, ...], target: _Buffer) -> None:
        """Write a padding record if that lets ``target``, one of ``parts``, go to the disk from the caller's
        memory; the parts follow ``ahead`` bytes from now (see the module docstring)."""
        if not isinstance(self._file, DirectFile):
            return
        for part in parts:
            if part is target:
                break
            ahead += _nbytes(part)
        gap = self._file.gap_before(target, ahead)
        if not gap:  # None (it would be staged anyway) or 0 (it is aligned already)
            return
        if gap < _RECORD_START.size:
            gap += BLOCK
        record = bytearray(gap)
        _RECORD_START.pack_into(record, 0, PADDING_OPCODE, gap - _RECORD_START.size)
        self._file.write(record)

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


def _close_synced(file: BinaryIO | DirectFile, directory: Path) -> None:
    """Finish and fsync a file, its directory first: when the file's fsync returns, its name is durable too."""
    fsync_directory(directory)
    if isinstance(file, DirectFile):
        file.close(sync=True)
        return
    file.flush()
    os.fsync(file.fileno())
    file.close()


def _compress(compression: str, parts: list[_Buffer], size: int) -> bytes:
    """The chunk's records compressed as one frame (zstd level 3 / lz4 frame, like the Python writer)."""
    if compression == "zstd":
        compressor = zstandard.ZstdCompressor().compressobj(size=size)
        return b"".join([*(compressor.compress(part) for part in parts), compressor.flush()])
    if compression == "lz4":
        return bytes(lz4.frame.compress(b"".join(parts)))
    raise ValueError(f"unknown chunk compression {compression!r}")


# --- repair after a failed write -------------------------------------------------------------


def _repair_file(
    path: Path, schemas: list[Schema], channels: list[Channel], serialized_metadata: str
) -> Totals | None:
    """Cut ``path`` after its last complete record and append a summary; ``None`` if impossible."""
    try:
        # Unbuffered, so a failed write leaves nothing behind that a later flush could append.
        with open(path, "r+b", buffering=0) as file:
            found = scan(file, file.seek(0, io.SEEK_END))
            units = found.units
            keep = len(units)
            metadata = serialized_metadata
            for _ in range(_REPAIR_ATTEMPTS):
                kept = units[:keep]
                if not found.start:  # not even the header made it: begin the file anew
                    base, head = 0, MAGIC + _header_record()
                elif kept and kept[-1].indexes is not None:  # the last chunk, with rebuilt indexes
                    base, head = kept[-1].record_end, kept[-1].indexes
                else:
                    base, head = kept[-1].end if kept else found.start, b""
                totals = Totals.of(kept)
                tail = head + summary_tail(
                    base + len(head), schemas, channels,
                    {METADATA_NAME: {METADATA_KEY: metadata}} if metadata else None, totals,
                    [unit.chunk_index for unit in kept if unit.chunk_index is not None],
                    [unit.metadata_index for unit in kept if unit.metadata_index is not None],
                )
                try:
                    file.truncate(base)
                    file.seek(base)
                    _write_all(file, tail)
                    fsync_directory(path.parent)
                    os.fsync(file.fileno())  # durable before metadata.yaml can name the file
                    return totals
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
