"""One storage file of a soak bag, read by two independent readers, in a worker process.

* ``baglib``'s reader reads every message: per topic the count and the largest message, and from each message
  its stream (topic, ``header.frame_id``), capture stamp and sequence number, parsed from the CDR bytes (Image
  and PointCloud2: ``data[0:8]``; Imu: ``orientation_covariance[1]``; std_msgs/String: the number it holds;
  CameraInfo has none, its stamp pairs it with its image);
* ``rosbags`` reads the file's index (the message count per topic, which must equal baglib's), decodes the
  first message of every topic (the CDR parser above must read the same fields from it), and reads every
  message of every topic whose messages are at most ``FULL_READ_MAX_BYTES``: all but the rig's 1080p frames
  and point clouds, which rosbags, copying each, reads at about one CPU second per 400 MB on the reference
  machine: as much CPU as the rig's whole data rate leaves.

What comes back (:class:`FileContent`) is small: sequence numbers as runs, stamps only of camera streams.
"""
from __future__ import annotations

import os
import struct
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import Any, Optional

IMAGE = "sensor_msgs/msg/Image"
CLOUD = "sensor_msgs/msg/PointCloud2"
IMU = "sensor_msgs/msg/Imu"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
STRING = "std_msgs/msg/String"
#: Message types whose stamps are kept: an image and its CameraInfo share one.
CAMERA_TYPES = (IMAGE, CAMERA_INFO)
FULL_READ_MAX_BYTES = 1 << 20
_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")
_F64 = struct.Struct("<d")

#: A stream: (topic, header.frame_id); one driver instance publishes one stream per topic.
Stream = tuple[str, str]
#: What one message says: (capture stamp ns, frame_id, sequence number or None).
Fields = tuple[int, str, Optional[int]]


@dataclass
class FileContent:
    """What one storage file holds, as the two readers saw it."""

    path: str
    size: int
    messages: int
    counts: dict[str, int]                       # baglib: messages per topic
    rosbags_index: dict[str, int]                # rosbags: the file's message count per topic
    rosbags_read: dict[str, int]                 # rosbags: messages read one by one, per topic
    runs: dict[Stream, list[tuple[int, int]]]    # sequence numbers: sorted, merged runs [first, last]
    duplicates: int                              # sequence numbers found twice in this file
    stamps: dict[Stream, list[int]]              # camera streams: every image / CameraInfo stamp
    replay: list[tuple[int, int]]                # std_msgs/String messages: (log time ns, number)
    seconds: float                               # wall time of the reading
    cpu_s: float = 0.0                           # the worker's CPU time for it
    problems: list[str] = field(default_factory=list)


class _Cdr:
    """A cursor over little-endian CDR (alignment counts from the end of the 4-byte encapsulation header)."""

    def __init__(self, data: bytes | memoryview) -> None:
        if data[1] != 1:
            raise ValueError("only little-endian CDR is expected")
        self.data = data
        self.pos = 4

    def _align(self, size: int) -> None:
        self.pos += -(self.pos - 4) % size

    def u32(self) -> int:
        self._align(4)
        (value,) = _U32.unpack_from(self.data, self.pos)
        self.pos += 4
        return value

    def f64(self) -> float:
        self._align(8)
        (value,) = _F64.unpack_from(self.data, self.pos)
        self.pos += 8
        return value

    def skip(self, size: int) -> None:
        self.pos += size

    def string(self) -> str:
        length = self.u32()
        text = bytes(self.data[self.pos:self.pos + max(0, length - 1)]).decode()
        self.pos += length
        return text

    def header(self) -> tuple[int, str]:
        sec, nanosec = _STAMP.unpack_from(self.data, self.pos)
        self.pos += 8
        return sec * 1_000_000_000 + nanosec, self.string()

    def leading_u64_of_sequence(self) -> int:
        """The first 8 bytes of a byte sequence (its length first), little-endian: a driver's number."""
        self.u32()
        return int.from_bytes(self.data[self.pos:self.pos + 8], "little")


def parse_fields(msgtype: str, data: bytes | memoryview) -> Fields:
    """(stamp, frame_id, sequence number) of one serialized message of the soak's types."""
    cdr = _Cdr(data)
    if msgtype == STRING:
        return 0, "", int(cdr.string())
    stamp, frame_id = cdr.header()
    if msgtype == IMAGE:
        cdr.u32(), cdr.u32(), cdr.string()  # height, width, encoding
        cdr.skip(1)                         # is_bigendian
        cdr.u32()                           # step
        return stamp, frame_id, cdr.leading_u64_of_sequence()
    if msgtype == CLOUD:
        cdr.u32(), cdr.u32()                # height, width
        for _ in range(cdr.u32()):          # fields: name, offset, datatype, count
            cdr.string(), cdr.u32(), cdr.skip(1), cdr.u32()
        cdr.skip(1)                         # is_bigendian
        cdr.u32(), cdr.u32()                # point_step, row_step
        return stamp, frame_id, cdr.leading_u64_of_sequence()
    if msgtype == IMU:
        for _ in range(4 + 1):              # orientation, orientation_covariance[0]
            cdr.f64()
        return stamp, frame_id, int(cdr.f64())
    return stamp, frame_id, None


def fields_by_rosbags(typestore: Any, data: bytes, msgtype: str) -> Fields:
    """The same fields, from rosbags' own deserialization."""
    msg = typestore.deserialize_cdr(data, msgtype)
    if msgtype == STRING:
        return 0, "", int(msg.data)
    stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
    if msgtype in (IMAGE, CLOUD):
        return stamp, msg.header.frame_id, int.from_bytes(bytes(msg.data[:8]), "little")
    if msgtype == IMU:
        return stamp, msg.header.frame_id, int(msg.orientation_covariance[1])
    return stamp, msg.header.frame_id, None


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


def read_file(path: str) -> FileContent:
    """Read the storage file ``path`` with both readers (module docstring)."""
    from baglib.read.reader import BagReader
    started, cpu = time.perf_counter(), time.process_time()
    numbers: dict[Stream, list[int]] = defaultdict(list)
    stamps: dict[Stream, list[int]] = defaultdict(list)
    replay: list[tuple[int, int]] = []
    counts: Counter[str] = Counter()
    largest: Counter[str] = Counter()
    with BagReader(path) as bag:
        for message in bag.messages():
            topic, msgtype = message.connection.topic, message.connection.msgtype
            counts[topic] += 1
            largest[topic] = max(largest[topic], len(message.data))
            stamp, frame_id, number = parse_fields(msgtype, message.data)
            if msgtype in CAMERA_TYPES:
                stamps[(topic, frame_id)].append(stamp)
            if msgtype == STRING:
                replay.append((message.log_time_ns, number))
            elif number is not None:
                numbers[(topic, frame_id)].append(number)
    content = FileContent(path, os.path.getsize(path), sum(counts.values()), dict(counts), {}, {}, {}, 0,
                          dict(stamps), replay, 0.0)
    for stream, values in numbers.items():
        content.runs[stream], duplicates = runs_of(values)
        content.duplicates += duplicates
    read_with_rosbags(content, largest)
    content.seconds, content.cpu_s = time.perf_counter() - started, time.process_time() - cpu
    return content


def read_with_rosbags(content: FileContent, largest: Counter[str]) -> None:
    """rosbags' part (module docstring); what disagrees with baglib goes into ``content.problems``."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    typestore = get_typestore(Stores.ROS2_JAZZY)
    index: Counter[str] = Counter()
    read: Counter[str] = Counter()
    with Reader(content.path) as reader:
        for connection in reader.connections:
            index[connection.topic] += connection.msgcount
            for _, _, raw in reader.messages(connections=[connection]):
                ours, theirs = parse_fields(connection.msgtype, raw), fields_by_rosbags(typestore, raw,
                                                                                         connection.msgtype)
                if ours != theirs:
                    content.problems.append(f"{connection.topic}: the CDR parser read {ours}, rosbags {theirs}")
                break
        small = [c for c in reader.connections if largest.get(c.topic, 0) <= FULL_READ_MAX_BYTES]
        for connection, _, _ in reader.messages(connections=small):
            read[connection.topic] += 1
    content.rosbags_index = {topic: count for topic, count in index.items() if count}  # baglib lists no empty topic
    content.rosbags_read = dict(read)
    if content.rosbags_index != content.counts:
        content.problems.append(f"message counts: baglib {content.counts}, rosbags' index {content.rosbags_index}")
    wrong = {t: (n, content.counts.get(t)) for t, n in read.items() if n != content.counts.get(t)}
    if wrong:
        content.problems.append(f"messages rosbags read one by one differ from baglib's (rosbags, baglib): {wrong}")
