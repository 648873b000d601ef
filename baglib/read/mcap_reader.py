"""Reading one ``.mcap`` storage file: rosbag2_storage_mcap's layout, or whatever part of it a crash left.

Where the messages are comes from the summary (chunk indexes, statistics) when the file has an intact
one. A file without it (a crash, a cut copy) is read linearly up to its first damage, exactly the
records ``bag recover`` would keep (:func:`.mcap_records.scan`); a summary without chunk indexes
(rosbag2's ``fastwrite`` preset writes no chunks) makes the top-level messages be listed from their
record headers. As with libmcap's indexed reading, top-level messages next to indexed chunks are not
read.

Messages come out in log-time order, equal times in file order, even when chunks overlap in time
or hold messages out of order: chunks are taken in order of their first log time, and a message
waits in a heap only while a later chunk could still hold an earlier one. In the usual file (chunks
in time order) nothing waits, and each message's data is a ``memoryview`` into its chunk's buffer:
the only copies are the read from the file and, for compressed chunks, the decompression.
"""
from __future__ import annotations

import bisect
import contextlib
import heapq
import io
import itertools
import logging
import os
import struct
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, ChunkIndex, Metadata, Schema
from mcap.stream_reader import StreamReader

from baglib.format.mcap_records import MAGIC, InvalidRecord, Totals, decompress, scan
from baglib.format.metadata import parse_qos_profiles
from baglib.read.storage_reader import BagReadError, ByteSource, FileTopic, RawMessage

__all__ = ["McapReader"]

_log = logging.getLogger(__name__)

# opcode and length of a record, then a message's channel id, sequence, log time and publish time
_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<BQHIQQ")
# a chunk record up to its compression name: opcode, length, start, end, uncompressed size, crc, name length
_CHUNK_HEAD = struct.Struct("<BQQQQII")
_METADATA_NAME = "rosbag2"  # rosbag2_storage_mcap's metadata record and its keys
_SERIALIZED_METADATA = "serialized_metadata"
_ROS_DISTRO = "ROS_DISTRO"
# Lists the top-level records of an unindexed file in blocks of this size.
_LIST_BLOCK = 1 << 20


@dataclass(frozen=True)
class _Unit:
    """A chunk (``chunk`` set) or one top-level message record, and the log times it spans."""

    start_ns: int
    end_ns: int
    offset: int
    length: int
    #: The channels with messages in it (``None``: unknown, so it must be read to know).
    channels: frozenset[int] | None
    chunk: ChunkIndex | None = None


class McapReader:
    """One MCAP file open for reading; safe to read from several threads (positioned reads only). ``source``:
    the file's bytes come from there (an object in a store) instead of from ``path``, which then only names it."""

    storage_id = "mcap"

    def __init__(self, path: Path, source: ByteSource | None = None) -> None:
        self.path = path
        self._source = source
        self._fd = -1
        if source is None:
            try:
                self._fd = os.open(path, os.O_RDONLY)
            except OSError as error:
                raise BagReadError(f"cannot open {path}: {error.strerror}") from error
        self._closed = False
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    def _open(self) -> None:
        size = os.fstat(self._fd).st_size if self._source is None else self._source.seek(0, io.SEEK_END)
        if self._read(len(MAGIC), 0) != MAGIC:
            raise BagReadError(f"{self.path} is not an MCAP file (no MCAP magic at its start)")
        schemas, channels, metadata = self._read_indexed(size) or self._read_linearly(size)
        self.topics = [_file_topic(channel, schemas.get(channel.schema_id), self.path)
                       for channel in sorted(channels.values(), key=lambda channel: channel.id)]
        rosbag2 = metadata.get(_METADATA_NAME, {})
        self.serialized_metadata = rosbag2.get(_SERIALIZED_METADATA, "")
        self.ros_distro = rosbag2.get(_ROS_DISTRO, "")

    def _read_indexed(self, size: int) -> tuple[dict[int, Schema], dict[int, Channel], dict[str, dict[str, str]]
                                                 ] | None:
        """Schemas, channels and metadata from the summary; sets the units (from its chunk indexes),
        counts and time range. ``None`` when the file has no usable summary."""
        with self._stream() as file:
            try:
                summary = SeekingReader(file).get_summary()
                metadata: dict[str, dict[str, str]] = {}
                for index in summary.metadata_indexes if summary is not None else ():
                    record = next(StreamReader(io.BytesIO(self._read(index.length, index.offset)),
                                               skip_magic=True).records, None)
                    if isinstance(record, Metadata):
                        metadata[record.name] = record.metadata
            except Exception:  # no footer (a cut file) or a damaged summary: the parser meets any bytes
                return None
        if summary is None or (not summary.channels and (summary.statistics is None
                                                        or summary.statistics.message_count)):
            return None
        if summary.chunk_indexes:
            self._set_units([_chunk_unit(index, frozenset(index.message_index_offsets) or None)
                             for index in summary.chunk_indexes])
        elif summary.statistics is None or summary.statistics.message_count:
            self._set_units(self._list_top_level_messages(size))
        else:
            self._set_units([])
        statistics = summary.statistics
        if statistics is not None:
            self._counts: dict[int, int] | None = dict(statistics.channel_message_counts)
            self._range = (statistics.message_start_time, statistics.message_end_time) \
                if statistics.message_count else None
        else:
            self._counts = None
            self._range = (min(unit.start_ns for unit in self._units), max(unit.end_ns for unit in self._units)) \
                if self._units else None
        return summary.schemas, summary.channels, metadata

    def _read_linearly(self, size: int) -> tuple[dict[int, Schema], dict[int, Channel], dict[str, dict[str, str]]]:
        """Schemas, channels and metadata of everything complete before the file's first damage, as
        ``bag recover`` keeps it; sets the units, counts and time range of those records."""
        with self._stream() as file:
            found = scan(file, size, check_chunks=True)
        if found.damage is not None:
            _log.warning("%s has no summary: %s; reading the %d complete records before offset %d",
                         self.path, found.damage.reason, len(found.units), found.damage.offset)
        units = []
        for unit in found.units:
            if unit.chunk_index is not None:
                units.append(_chunk_unit(unit.chunk_index, frozenset(unit.counts)))
            elif unit.counts and unit.first_ns is not None:  # a top-level message
                units.append(_Unit(unit.first_ns, unit.first_ns, unit.start, unit.end - unit.start,
                                   frozenset(unit.counts)))
        self._set_units(units)
        totals = Totals.of(found.units)
        self._counts = totals.counts
        self._range = None if totals.first_ns is None or totals.last_ns is None else (totals.first_ns, totals.last_ns)
        return found.schemas, found.channels, found.metadata

    def _set_units(self, units: list[_Unit]) -> None:
        """Keep ``units`` ordered by first log time (then file offset), with what a time seek needs: the
        first log times, and the latest log time reached by each prefix of the list."""
        self._units = sorted(units, key=lambda unit: (unit.start_ns, unit.offset))
        self._starts = [unit.start_ns for unit in self._units]
        self._reach = list(itertools.accumulate((unit.end_ns for unit in self._units), max))

    def _list_top_level_messages(self, size: int) -> list[_Unit]:
        """The units of a file whose summary has no chunk indexes, from the record headers alone."""
        units = []
        header_length = _RECORD.unpack(self._read(_RECORD.size, len(MAGIC)))[1]
        position = len(MAGIC) + _RECORD.size + header_length
        while position + _RECORD.size <= size:
            head = self._read(_MESSAGE.size, position)
            opcode, length = _RECORD.unpack_from(head)
            end = position + _RECORD.size + length
            if opcode == Opcode.DATA_END or end > size:
                break
            if opcode == Opcode.MESSAGE and len(head) == _MESSAGE.size:
                _, _, channel_id, _, log_time, _ = _MESSAGE.unpack(head)
                units.append(_Unit(log_time, log_time, position, end - position, frozenset((channel_id,))))
            elif opcode == Opcode.CHUNK:
                units.append(self._chunk_from_header(position, end))
            position = end
        return units

    def _chunk_from_header(self, position: int, end: int) -> _Unit:
        head = self._read(_CHUNK_HEAD.size, position)
        _, _, start_ns, end_ns, uncompressed_size, _, name_length = _CHUNK_HEAD.unpack(head)
        compression = self._read(name_length, position + _CHUNK_HEAD.size).decode()
        data_offset = position + _CHUNK_HEAD.size + name_length + 8
        index = ChunkIndex(message_start_time=start_ns, message_end_time=end_ns, chunk_start_offset=position,
                           chunk_length=end - position, message_index_offsets={}, message_index_length=0,
                           compression=compression, compressed_size=end - data_offset,
                           uncompressed_size=uncompressed_size)
        return _chunk_unit(index, None)

    # --- the StorageReader interface ----------------------------------------------------------

    def time_range(self) -> tuple[int, int] | None:
        return self._range

    def message_counts(self) -> dict[int, int]:
        if self._counts is None:
            counts: dict[int, int] = {}
            for key, _, _, _ in self.messages(None, None, None):
                counts[key] = counts.get(key, 0) + 1
            self._counts = counts
        return dict(self._counts)

    def messages(self, keys: Collection[int] | None, start_ns: int | None, stop_ns: int | None
                 ) -> Iterator[RawMessage]:
        wanted = frozenset(topic.key for topic in self.topics) if keys is None else frozenset(keys)
        start = -1 if start_ns is None else start_ns
        stop = 2**64 if stop_ns is None else stop_ns
        # Units before `first` end before `start`; those from `last` on begin at or after `stop`.
        first, last = bisect.bisect_left(self._reach, start), bisect.bisect_left(self._starts, stop)
        units = [unit for unit in self._units[first:last]
                 if unit.end_ns >= start and (unit.channels is None or not unit.channels.isdisjoint(wanted))]
        waiting: list[tuple[int, int, int, int, int, bytes | memoryview]] = []
        for number, unit in enumerate(units):
            while waiting and waiting[0][0] < unit.start_ns:
                entry = heapq.heappop(waiting)
                yield entry[3], entry[0], entry[4], entry[5]
            found = self._unit_messages(unit, wanted, start, stop)
            following = units[number + 1].start_ns if number + 1 < len(units) else 2**64
            if not waiting and _in_order(found):
                # Nothing waits and nothing later can come before these: out they go, as read.
                cut = len(found)
                while cut and found[cut - 1][1] >= following:
                    cut -= 1
                for channel_id, log_time, publish_time, _, data in found[:cut]:
                    yield channel_id, log_time, publish_time, data
                found = found[cut:]
            for channel_id, log_time, publish_time, position, data in found:
                heapq.heappush(waiting, (log_time, unit.offset, position, channel_id, publish_time, data))
        while waiting:
            entry = heapq.heappop(waiting)
            yield entry[3], entry[0], entry[4], entry[5]

    def close(self) -> None:
        self._closed = True
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    # --- reading units ------------------------------------------------------------------------

    def _unit_messages(self, unit: _Unit, wanted: frozenset[int], start: int, stop: int
                       ) -> list[tuple[int, int, int, int, memoryview]]:
        """The unit's messages of the ``wanted`` channels in ``[start, stop)``, in file order, as
        (channel id, log time, publish time, position in the unit, data)."""
        if unit.chunk is None:
            buffer = memoryview(self._pread(unit.length, unit.offset))
            end = len(buffer)
        else:
            buffer = memoryview(self._chunk_content(unit.chunk))
            end = unit.chunk.uncompressed_size
        found = []
        position = 0
        unpack = _MESSAGE.unpack_from
        message = Opcode.MESSAGE
        while position < end:
            if end - position < _RECORD.size:
                raise self._damaged(unit, "a record header cut short")
            opcode, length = _RECORD.unpack_from(buffer, position)
            record_end = position + _RECORD.size + length
            if record_end > end:
                raise self._damaged(unit, "a record longer than its chunk")
            if opcode == message:
                if length < _MESSAGE.size - _RECORD.size:
                    raise self._damaged(unit, "a message record too short")
                _, _, channel_id, _, log_time, publish_time = unpack(buffer, position)
                if channel_id in wanted and start <= log_time < stop:
                    found.append((channel_id, log_time, publish_time, position,
                                  buffer[position + _MESSAGE.size:record_end]))
            position = record_end
        return found

    def _chunk_content(self, chunk: ChunkIndex) -> bytes:
        data_offset = chunk.chunk_start_offset + _CHUNK_HEAD.size + len(chunk.compression.encode()) + 8
        data = self._pread(chunk.compressed_size, data_offset)
        try:
            content = decompress(chunk.compression, data, chunk.uncompressed_size)
        except InvalidRecord as error:
            raise BagReadError(f"{self.path}: chunk at offset {chunk.chunk_start_offset}: {error}") from error
        if len(content) != chunk.uncompressed_size:
            raise BagReadError(f"{self.path}: chunk at offset {chunk.chunk_start_offset} holds "
                               f"{len(content)} bytes, its header says {chunk.uncompressed_size}")
        return content

    def _pread(self, length: int, offset: int) -> bytes:
        if self._closed:
            raise BagReadError(f"{self.path} is closed")
        data = self._read(length, offset)
        if len(data) != length:
            raise BagReadError(f"{self.path} ends at offset {offset + len(data)}, inside a record its index "
                               f"places at {offset} (was the file cut after it was indexed?)")
        return data

    def _read(self, length: int, offset: int) -> bytes:
        """Up to ``length`` bytes at ``offset``, from the file or the source."""
        return os.pread(self._fd, length, offset) if self._source is None else self._source.pread(length, offset)

    def _stream(self) -> contextlib.AbstractContextManager[BinaryIO]:
        """The file (or the source) as a seekable binary stream at its start, for the mcap library's readers."""
        if self._source is None:
            return open(self._fd, "rb", closefd=False)
        self._source.seek(0)
        return contextlib.nullcontext(self._source)

    def _damaged(self, unit: _Unit, what: str) -> BagReadError:
        return BagReadError(f"{self.path}: {what} in the {'chunk' if unit.chunk else 'record'} at offset "
                            f"{unit.offset}")


def _in_order(found: list[tuple[int, int, int, int, memoryview]]) -> bool:
    return all(found[index][1] <= found[index + 1][1] for index in range(len(found) - 1))


def _chunk_unit(index: ChunkIndex, channels: frozenset[int] | None) -> _Unit:
    return _Unit(index.message_start_time, index.message_end_time, index.chunk_start_offset,
                 index.chunk_length, channels, index)


def _file_topic(channel: Channel, schema: Schema | None, path: Path) -> FileTopic:
    """The channel as a topic: type from its schema, QoS and type hash from rosbag2's channel metadata."""
    try:
        profiles = tuple(parse_qos_profiles(channel.metadata.get("offered_qos_profiles")))
    except ValueError as error:
        _log.warning("%s: channel %s: %s; its QoS profiles are left out", path, channel.topic, error)
        profiles = ()
    definition = None
    if schema is not None and schema.encoding:  # an empty text with an encoding describes an empty message
        definition = (schema.encoding, bytes(schema.data).decode(errors="replace"))
    return FileTopic(channel.id, channel.topic, schema.name if schema is not None else "",
                     channel.message_encoding, profiles, channel.metadata.get("topic_type_hash", ""), definition)
