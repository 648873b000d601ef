"""What a crash state must hold, and the check of one state: recover in place, read three ways, compare.

Reference: the finished bag of the capture, every message with its topic, the driver's sequence number (camera:
the first 8 bytes of ``Image.data``; IMU: ``orientation_covariance[1]``), its receive time (the log time) and
its exact CDR bytes.

"Written": a message is *written* at the first moment after which a SIGKILL would leave it in the file as a
complete record (``storage.flush_interval``'s notion: MCAP, the chunk holding it is whole in the file; SQLite3,
its transaction committed: the rollback journal is gone). It is found on the trace itself: the SIGKILL state at
a cut is every done operation applied (the page cache), and the set of messages a plain stream reader finds
there grows with the cut, so a bisection over the cut positions gives every message's moment.

A crash state at a cut (time ``t_cut``) must then hold

* **sync bound** (the guarantee of docs/recorder.md): every message written more than ``sync_interval`` +
  ``slack`` before ``t_cut`` (slack: the writer checks its sync deadline at least every 0.2 s, plus one fsync);
* **fsync durability**: every message written before the start of an fsync of its file that returned before
  the cut (what the writer made durable must be there, whatever the timing);

and, whatever it holds: no message twice, every message byte for byte the recorded one, the same messages
through ``rosbags.rosbag2.Reader``, the mcap reader (MCAP; with its summary) or sqlite3 (SQLite3), and
``bag info``'s counts equal to what the readers read and no warning left. ``bag recover`` must not raise.
"""
from __future__ import annotations

import collections
import contextlib
import dataclasses
import io
import re
import shutil
import sqlite3
import struct
from pathlib import Path

from mcap.reader import make_reader
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from baglib.tools.info import format_bag_info
from baglib.tools.repair import recover_bag

from .model import BagModel, CrashState

__all__ = ["Reference", "Visibility", "Outcome", "check_state", "read_reference", "visibility"]

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
Key = tuple[str, int]  # (topic, sequence number)


def sequence(topic: str, cdr: bytes) -> int:
    """The driver's sequence number of a recorded message."""
    if topic == "/imu/imu":
        return int(TYPESTORE.deserialize_cdr(cdr, "sensor_msgs/msg/Imu").orientation_covariance[1])
    message = TYPESTORE.deserialize_cdr(cdr, "sensor_msgs/msg/Image")
    return struct.unpack_from("<Q", bytes(message.data[:8]))[0]


@dataclasses.dataclass
class Reference:
    """Every message the recording wrote: key -> (CDR bytes, receive time in s); and bytes -> key."""

    messages: dict[Key, tuple[bytes, float]]
    by_bytes: dict[tuple[str, bytes], Key]

    def identify(self, topic: str, cdr: bytes) -> Key | None:
        """The key of a read message, None if its bytes are not a recorded message's (corrupted)."""
        return self.by_bytes.get((topic, bytes(cdr)))

    def describe(self, topic: str, cdr: bytes) -> str:
        try:
            return f"{topic} #{sequence(topic, bytes(cdr))} ({len(cdr)} bytes, not the recorded bytes)"
        except Exception:  # noqa: BLE001 - damaged beyond decoding
            return f"{topic}: {len(cdr)} undecodable bytes"


def read_reference(bag: Path) -> Reference:
    messages: dict[Key, tuple[bytes, float]] = {}
    by_bytes: dict[tuple[str, bytes], Key] = {}
    with Reader(bag) as reader:
        for connection, timestamp, raw in reader.messages():
            raw = bytes(raw)
            key = (connection.topic, sequence(connection.topic, raw))
            if key in messages:
                raise ValueError(f"the reference bag {bag} holds {key} twice")
            messages[key] = (raw, timestamp / 1e9)
            by_bytes[(connection.topic, raw)] = key
    return Reference(messages, by_bytes)


# --- SIGKILL visibility ---------------------------------------------------------------------------


def stream_read(state: CrashState, reference: Reference, scratch: Path, storage: str) -> dict[Key, str]:
    """The messages a plain reader finds in a state without repairing it (key -> file name): complete MCAP
    records up to the first damage; the rows sqlite shows (a hot journal rolled back)."""
    found: dict[Key, str] = {}
    if storage == "mcap":
        for name, content in state.files.items():
            if not name.endswith(".mcap"):
                continue
            channels: dict[int, str] = {}
            with contextlib.suppress(Exception):  # the file's end or first damage: what came before counts
                for record in StreamReader(io.BytesIO(content), skip_magic=False).records:
                    if isinstance(record, Channel):
                        channels[record.id] = record.topic
                    elif isinstance(record, Message) and record.channel_id in channels:
                        key = reference.identify(channels[record.channel_id], record.data)
                        if key is not None:
                            found.setdefault(key, name)
        return found
    shutil.rmtree(scratch, ignore_errors=True)
    bag = state.materialize(scratch)
    if bag is None:
        return found
    for path in sorted(bag.glob("*.db3")):
        with contextlib.suppress(sqlite3.Error), contextlib.closing(sqlite3.connect(path)) as db:
            rows = db.execute("SELECT topics.name, messages.data FROM messages JOIN topics "
                              "ON topics.id = messages.topic_id").fetchall()
            for topic, data in rows:
                key = reference.identify(topic, data)
                if key is not None:
                    found.setdefault(key, path.name)
    shutil.rmtree(scratch, ignore_errors=True)
    return found


@dataclasses.dataclass
class Visibility:
    """Per message: the cut position from which a SIGKILL keeps it, the file then holding it (inode) and
    the time of the operation that completed it."""

    position: dict[Key, int]
    entered: dict[Key, int]  # entry line of the operation that completed it (it may show from a cut after it)
    inode: dict[Key, int]
    time: dict[Key, float]
    evaluations: int
    non_monotonic: int  # messages seen at one cut and gone at a later one (should be 0)
    never: list[Key]  # recorded but never visible after a SIGKILL before the end (should be none)


def visibility(model: BagModel, reference: Reference, storage: str, scratch: Path) -> Visibility:
    positions = model.positions
    cache: dict[int, dict[Key, str]] = {}

    def seen(index: int) -> dict[Key, str]:
        if index not in cache:
            cache[index] = stream_read(model.sigkill_state(positions[index]), reference, scratch, storage)
        return cache[index]

    found: dict[Key, int] = {}
    non_monotonic = 0

    def solve(lo: int, hi: int) -> None:
        nonlocal non_monotonic
        before, after = seen(lo), seen(hi)
        non_monotonic += len(before.keys() - after.keys())
        if not after.keys() - before.keys():
            return
        if hi - lo == 1:
            for key in after.keys() - before.keys():
                found[key] = hi
            return
        middle = (lo + hi) // 2
        solve(lo, middle)
        solve(middle, hi)

    solve(0, len(positions) - 1)
    position = {key: positions[index] for key, index in found.items()}
    inode: dict[Key, int] = {}
    names_to_inode = _names_at_end(model)
    for key, index in found.items():
        inode[key] = names_to_inode.get(seen(index)[key], -1)
    times = {key: model.trace.line_times[pos - 1] for key, pos in position.items()}
    entry_of_exit = {op.seq_out: op.seq_in for op in model.ops}
    entered = {key: entry_of_exit.get(pos - 1, pos - 1) for key, pos in position.items()}
    never = sorted(set(reference.messages) - set(found))
    return Visibility(position, entered, inode, times, len(cache), non_monotonic, never)


def _names_at_end(model: BagModel) -> dict[str, int]:
    """Storage file name -> inode (storage files are never renamed or reused)."""
    return {op.name: op.ino for op in model.ops if op.kind == "create" and op.dir == model.bag_ino}


# --- checking a crash state -----------------------------------------------------------------------


@dataclasses.dataclass
class Outcome:
    failures: list[str]
    present: int
    required_sync: int
    required_fsync: int
    lost: int  # recorded messages received before the cut and not in the recovered bag
    oldest_lost_age: float  # how long before the cut the oldest of them was received (0: none lost)
    recovered: str  # the recover report, for failures


def _readers(bag: Path, storage: str) -> tuple[dict[str, list[tuple[str, bytes]]], list[str]]:
    """The messages (topic, bytes) each reader reads from a recovered bag, and the readers' errors."""
    reads: dict[str, list[tuple[str, bytes]]] = {}
    errors: list[str] = []
    try:
        with Reader(bag) as reader:
            reads["rosbags"] = [(connection.topic, bytes(raw)) for connection, _, raw in reader.messages()]
    except Exception as error:  # noqa: BLE001
        errors.append(f"rosbags cannot read the recovered bag: {error!r}")
    listed = _listed_files(bag)
    if storage == "mcap":
        messages: list[tuple[str, bytes]] = []
        try:
            for name in listed:
                with open(bag / name, "rb") as stream:
                    reader = make_reader(stream)
                    if reader.get_summary() is None:
                        errors.append(f"{name}: no summary after recover")
                    messages += [(channel.topic, bytes(message.data))
                                 for _, channel, message in reader.iter_messages()]
            reads["mcap"] = messages
        except Exception as error:  # noqa: BLE001
            errors.append(f"mcap reader: {error!r}")
    else:
        messages = []
        try:
            for name in listed:
                with contextlib.closing(sqlite3.connect(f"file:{bag / name}?mode=ro", uri=True)) as db:
                    messages += [(topic, bytes(data)) for topic, data in db.execute(
                        "SELECT topics.name, messages.data FROM messages JOIN topics "
                        "ON topics.id = messages.topic_id ORDER BY messages.timestamp")]
            reads["sqlite3"] = messages
        except Exception as error:  # noqa: BLE001
            errors.append(f"sqlite3: {error!r}")
    return reads, errors


def _listed_files(bag: Path) -> list[str]:
    import yaml

    document = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    return list(document["relative_file_paths"])


_INFO_TOPIC = re.compile(r"Topic: (\S+) \| Type: \S+ \| Count: (\d+) \|")
_INFO_TOTAL = re.compile(r"^Messages:\s+(\d+)$", re.M)


def check_state(model: BagModel, state: CrashState, reference: Reference, seen: Visibility, storage: str,
                directory: Path, sync_interval: float = 1.0, slack: float = 0.5) -> Outcome:
    """Materialize the state into ``directory`` (a fresh path named as the bag), recover it in place, read it,
    and compare with what it must hold."""
    failures: list[str] = []
    frontiers, _ = model._frontiers(state.cut)  # noqa: SLF001 - the model's own durability frontier
    bound = state.t_cut - sync_interval - slack
    required_sync = {key for key, t in seen.time.items() if t <= bound}
    required_fsync = {key for key, pos in seen.position.items() if frontiers.get(seen.inode[key], -1) >= pos}
    bag = state.materialize(directory)
    present: collections.Counter[Key] = collections.Counter()
    recovered = ""
    if bag is not None:
        try:
            report = recover_bag(bag)
            recovered = report.text()
        except Exception as error:  # noqa: BLE001 - recover must report, never raise
            failures.append(f"bag recover raised {error!r}")
            report = None
        if report is not None and report.readable:
            reads, errors = _readers(bag, storage)
            failures += errors
            counts: dict[str, collections.Counter[Key]] = {}
            future: set[Key] = set()
            for reader, messages in reads.items():
                counted: collections.Counter[Key] = collections.Counter()
                for topic, data in messages:
                    key = reference.identify(topic, data)
                    if key is None:
                        failures.append(f"{reader}: corrupted message {reference.describe(topic, data)}")
                        continue
                    counted[key] += 1
                    if key in seen.entered and seen.entered[key] >= state.cut:
                        future.add(key)
                twice = sorted(key for key, count in counted.items() if count > 1)
                if twice:
                    failures.append(f"{reader}: {len(twice)} messages twice, e.g. {twice[:3]}")
                counts[reader] = counted
            if future:
                failures.append(f"{len(future)} messages whose write had not begun at the cut are there (uncommitted "
                                f"data, or a model error): {_keys(sorted(future))}")
            if len({frozenset(c.items()) for c in counts.values()}) > 1:
                failures.append("the readers disagree: " + ", ".join(f"{r} {sum(c.values())}"
                                                                       for r, c in counts.items()))
            present = next(iter(counts.values()), collections.Counter())
            try:
                info = format_bag_info(bag)
                total = int(_INFO_TOTAL.search(info).group(1))
                per_topic = {topic: int(count) for topic, count in _INFO_TOPIC.findall(info)}
                read_topics = collections.Counter(topic for topic, _ in present.elements())
                if total != sum(present.values()) or any(per_topic.get(t, 0) != n for t, n in read_topics.items()) \
                        or any(n and t not in read_topics for t, n in per_topic.items()):
                    failures.append(f"bag info counts {total} {per_topic}, the readers read "
                                    f"{sum(present.values())} {dict(read_topics)}")
                if "Warning:" in info:
                    failures.append("bag info still warns after recover: " + info[info.index("Warning:"):][:200])
            except Exception as error:  # noqa: BLE001
                failures.append(f"bag info failed: {error!r}")
    missing_sync = sorted(required_sync - set(present))
    missing_fsync = sorted(required_fsync - set(present))
    if missing_sync:
        oldest = min(seen.time[key] for key in missing_sync)
        failures.append(f"{len(missing_sync)} of {len(required_sync)} messages written more than sync_interval + "
                        f"slack ({sync_interval + slack:.2f} s) before the cut are missing, the oldest written "
                        f"{state.t_cut - oldest:.3f} s before it: {_keys(missing_sync)}")
    if missing_fsync:
        failures.append(f"{len(missing_fsync)} of {len(required_fsync)} messages covered by a completed fsync of "
                        f"their file are missing: {_keys(missing_fsync)}")
    received = {key for key, (_, t) in reference.messages.items() if t <= state.t_cut}
    lost = received - set(present)  # what the user loses: received before the cut, not in the recovered bag
    oldest_lost = max((state.t_cut - reference.messages[key][1] for key in lost), default=0.0)
    return Outcome(failures, sum(present.values()), len(required_sync), len(required_fsync), len(lost),
                   oldest_lost, recovered)


def _keys(keys: list[Key]) -> str:
    by_topic: dict[str, list[int]] = collections.defaultdict(list)
    for topic, seq in keys:
        by_topic[topic].append(seq)
    return "; ".join(f"{topic} #{_ranges(seqs)}" for topic, seqs in sorted(by_topic.items()))


def _ranges(values: list[int]) -> str:
    values = sorted(values)
    parts = []
    start = previous = values[0]
    for value in values[1:] + [None]:  # type: ignore[list-item]
        if value is not None and value == previous + 1:
            previous = value
            continue
        parts.append(f"{start}" if start == previous else f"{start}-{previous}")
        if value is not None:
            start = previous = value
    return ",".join(parts[:6]) + (" ..." if len(parts) > 6 else "")
