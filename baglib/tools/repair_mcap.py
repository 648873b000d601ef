"""Repairing an MCAP file a crash left unfinished: every record up to the first damage (``mcap_records`` checks
every chunk), with message indexes, statistics and the summary rebuilt, as ``mcap recover`` does. In place when
the records before the cut can stay where they are (a journaled patch, see ``patch_journal``), else by a copy."""
from __future__ import annotations

import contextlib
import os
import struct
import zlib
from pathlib import Path
from typing import Any

import yaml
from mcap.opcode import Opcode

from baglib.format.mcap_records import MAGIC, Scan, Totals, scan, summary_tail
from baglib.format.metadata import FileInfo
from baglib.tools.patch_journal import Patch
from baglib.tools.recovered import FileReport, Recovered, custom_data_of, load_yaml, topic_of
from baglib.write.mcap_storage import METADATA_KEY, METADATA_NAME

__all__ = ["recover_mcap"]

_COPY_BLOCK = 1 << 20
_FOOTER_LENGTH = 1 + 8 + 8 + 8 + 4


def recover_mcap(path: Path) -> Recovered:
    report = FileReport(path.name)
    with open(path, "rb") as file:
        size = os.fstat(file.fileno()).st_size
        found = scan(file, size, check_chunks=True)
        intact = found.damage is None and found.data_end is not None and _summary_intact(file, size, found)
    if not found.start:
        report.action = "left out"
        report.reasons.append(found.damage.reason if found.damage else "no header")
        return Recovered(report, FileInfo(path.name), [], None, None)
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
        topic = topic_of(report, channel.topic, schema.name if schema else "", channel.message_encoding,
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
        custom_data = custom_data_of(load_yaml(found.metadata.get(METADATA_NAME, {}).get(METADATA_KEY, "")))
    info = FileInfo.from_log_times(path.name, totals.first_ns, totals.last_ns, counts)

    def write(temporary: Path, serialized_metadata: str) -> None:
        _write_mcap(path, temporary, found, totals, serialized_metadata)

    def patch(serialized_metadata: str) -> Patch | None:
        return _mcap_patch(path, found, totals, serialized_metadata)

    return Recovered(report, info, topics, custom_data, None if intact else write, None if intact else patch)


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
