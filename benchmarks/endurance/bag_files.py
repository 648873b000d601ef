"""One storage file of a soak bag, read in a worker process: every message's stream, stamp and number
(message_fields), and the file checked by independent readers.

How much is read depends on the file's size:

* **a file up to** :data:`FULL_READ_FILE_BYTES` (the short run's): ``baglib``'s reader reads every message, and
  ``rosbags`` reads every message too (its count per topic, and its index, must equal baglib's);
* **a larger file** (the S1 rig's: 4 GB per 10 s): reading it whole twice, while the rig records 405 MB/s more,
  takes the disk and most of a 2-core machine from the recorder. The file's MCAP message indexes say where
  every message is; the ``mcap`` library reads the summary, and the first :data:`HEAD_BYTES` of every message
  are read from there (a positioned read each, without read-ahead): every number is still read, from 1/5000 of
  the bytes of a 1080p frame. ``baglib`` opens the file (its counts per topic must equal the index's), and
  ``rosbags`` reads its index (the same) and decodes the first message of every topic.

Either way the CDR parser is checked against rosbags' deserialization on the first message of every topic.
What comes back (:class:`FileContent`) is small: numbers as runs, stamps only of camera streams.
"""
from __future__ import annotations

import os
import struct
import time
from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field

from benchmarks.endurance.message_fields import (CAMERA_TYPES, HEAD_BYTES, STRING, Stream, fields_by_rosbags,
                                                 parse_fields)

FULL_READ_FILE_BYTES = 512 * 2**20
# MCAP records: a message's opcode, length, channel id, sequence, log time and publish time; a message index's
# opcode, length, channel id and the byte length of its (log time, offset) entries
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_INDEX_HEAD = struct.Struct("<BQHI")
_INDEX_ENTRY = struct.Struct("<QQ")
_MESSAGE_OPCODE, _INDEX_OPCODE = 0x05, 0x07
#: (topic, message type, log time ns, the message's serialized bytes or their first HEAD_BYTES)
Message = tuple[str, str, int, bytes]


@dataclass
class FileContent:
    """What one storage file holds, as the readers saw it."""

    path: str
    size: int
    messages: int
    counts: dict[str, int]                       # messages per topic (baglib's whole read, or the indexes')
    rosbags_index: dict[str, int]                # rosbags: the file's message count per topic
    rosbags_read: dict[str, int]                 # rosbags: messages read one by one, per topic
    runs: dict[Stream, list[tuple[int, int]]]    # sequence numbers: sorted, merged runs [first, last]
    duplicates: int                              # sequence numbers found twice in this file
    stamps: dict[Stream, list[int]]              # camera streams: every image / CameraInfo stamp
    replay: list[tuple[int, int]]                # std_msgs/String messages: (log time ns, number)
    seconds: float                               # wall time of the reading
    cpu_s: float = 0.0                           # the worker's CPU time for it
    heads_only: bool = False                     # read through the message indexes (module docstring)
    problems: list[str] = field(default_factory=list)


def runs_of(numbers: list[int]) -> tuple[list[tuple[int, int]], int]:
    """Sorted runs of consecutive numbers, and how many numbers occurred more than once."""
    unique = sorted(set(numbers))
    runs: list[list[int]] = []
    for number in unique:
        if runs and number == runs[-1][1] + 1:
            runs[-1][1] = number
        else:
            runs.append([number, number])
    return [(first, last) for first, last in runs], len(numbers) - len(unique)


def lower_priority() -> None:
    """The worker's initializer: the container and the churn come first."""
    os.nice(10)


def whole_messages(path: str) -> Iterator[Message]:
    """Every message of the file, read by baglib."""
    from baglib.read.reader import BagReader
    with BagReader(path) as bag:
        for message in bag.messages():
            yield message.connection.topic, message.connection.msgtype, message.log_time_ns, message.data


def message_heads(path: str) -> Iterator[Message]:
    """Every message's first HEAD_BYTES, found through the file's MCAP message indexes (uncompressed chunks)."""
    from mcap.reader import SeekingReader
    with open(path, "rb") as file:
        summary = SeekingReader(file).get_summary()
        if summary is None or not summary.chunk_indexes:
            raise ValueError("no summary with chunk indexes")
        fd = file.fileno()
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_RANDOM)  # one page per message, not a read-ahead window
        for chunk in summary.chunk_indexes:
            if chunk.compression:
                raise ValueError(f"a chunk compressed with {chunk.compression}")
            records = chunk.chunk_start_offset + 1 + 8 + 8 + 8 + 8 + 4 + 4 + 8  # chunk record head, no compression
            indexes = os.pread(fd, chunk.message_index_length, chunk.chunk_start_offset + chunk.chunk_length)
            for channel_id, entries in _message_indexes(indexes):
                channel = summary.channels[channel_id]
                msgtype = summary.schemas[channel.schema_id].name
                for log_time, offset in entries:
                    raw = os.pread(fd, _MESSAGE_HEAD.size + HEAD_BYTES, records + offset)
                    opcode, length, found, _, logged, _ = _MESSAGE_HEAD.unpack_from(raw)
                    if (opcode, found, logged) != (_MESSAGE_OPCODE, channel_id, log_time):
                        raise ValueError(f"no message of channel {channel_id} at {log_time} where its index says")
                    yield channel.topic, msgtype, log_time, raw[_MESSAGE_HEAD.size:_MESSAGE_HEAD.size + length - 22]


def _message_indexes(block: bytes) -> Iterator[tuple[int, list[tuple[int, int]]]]:
    """The (channel id, [(log time, offset)]) of the message index records after a chunk."""
    position = 0
    while position < len(block):
        opcode, length, channel_id, entries_length = _INDEX_HEAD.unpack_from(block, position)
        if opcode != _INDEX_OPCODE:
            raise ValueError(f"record {opcode:#x} among a chunk's message indexes")
        start = position + _INDEX_HEAD.size
        yield channel_id, [_INDEX_ENTRY.unpack_from(block, start + 16 * n) for n in range(entries_length // 16)]
        position += 9 + length


def read_file(path: str) -> FileContent:
    """Read the storage file ``path`` (module docstring)."""
    started, cpu = time.perf_counter(), time.process_time()
    heads_only = os.path.getsize(path) > FULL_READ_FILE_BYTES
    content = tally(path, message_heads(path) if heads_only else whole_messages(path))
    content.heads_only = heads_only
    if heads_only:
        check_baglib_counts(content)
    read_with_rosbags(content, every_message=not heads_only)
    content.seconds, content.cpu_s = time.perf_counter() - started, time.process_time() - cpu
    return content


def tally(path: str, messages: Iterator[Message]) -> FileContent:
    """Counts, number runs, camera stamps and the player's messages of ``messages``."""
    numbers: dict[Stream, list[int]] = defaultdict(list)
    stamps: dict[Stream, list[int]] = defaultdict(list)
    replay: list[tuple[int, int]] = []
    counts: Counter[str] = Counter()
    for topic, msgtype, log_time, data in messages:
        counts[topic] += 1
        stamp, frame_id, number = parse_fields(msgtype, data)
        if msgtype in CAMERA_TYPES:
            stamps[(topic, frame_id)].append(stamp)
        if msgtype == STRING:
            replay.append((log_time, number))
        elif number is not None:
            numbers[(topic, frame_id)].append(number)
    content = FileContent(path, os.path.getsize(path), sum(counts.values()), dict(counts), {}, {}, {}, 0,
                          dict(stamps), replay, 0.0)
    for stream, values in numbers.items():
        content.runs[stream], duplicates = runs_of(values)
        content.duplicates += duplicates
    return content


def check_baglib_counts(content: FileContent) -> None:
    """baglib opens the file: its message count per topic must equal what the indexes listed."""
    from baglib.read.reader import BagReader
    with BagReader(content.path) as bag:
        counts = {connection.topic: connection.message_count for connection in bag.connections
                  if connection.message_count}
    if counts != content.counts:
        content.problems.append(f"message counts: indexes {content.counts}, baglib {counts}")


def read_with_rosbags(content: FileContent, every_message: bool) -> None:
    """rosbags' part (module docstring); what disagrees goes into ``content.problems``."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    typestore = get_typestore(Stores.ROS2_JAZZY)
    index: Counter[str] = Counter()
    read: Counter[str] = Counter()
    with Reader(content.path) as reader:
        for connection in reader.connections:
            index[connection.topic] += connection.msgcount
            for _, _, raw in reader.messages(connections=[connection]):
                ours, theirs = (parse_fields(connection.msgtype, raw),
                                fields_by_rosbags(typestore, raw, connection.msgtype))
                if ours != theirs:
                    content.problems.append(f"{connection.topic}: the CDR parser read {ours}, rosbags {theirs}")
                break
        for connection, _, _ in reader.messages() if every_message else ():
            read[connection.topic] += 1
    content.rosbags_index = {topic: count for topic, count in index.items() if count}  # baglib lists no empty topic
    content.rosbags_read = dict(read)
    if content.rosbags_index != content.counts:
        content.problems.append(f"message counts: {content.counts} read, rosbags' index {content.rosbags_index}")
    if every_message and content.rosbags_read != content.counts:
        content.problems.append(f"messages rosbags read one by one {content.rosbags_read} != {content.counts}")
