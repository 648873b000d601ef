"""The soak's recorders: each one's bag files collected as they close, read in the worker, and its bag checked
once it is finalized.

A recorder splits every few seconds and keeps only its newest files (``storage.max_bag_files``). Every file it
lists in ``metadata.yaml`` is a finished one; the soak polls that file, hard-links each newly listed file into
a directory of its own (so the recorder's circular deletion cannot take it away before it is read) and hands
the link to the worker (bag_files.read_file), which reads it with baglib and rosbags; the link is removed once
read. When the recorder has been stopped and unloaded and all its files are read, its bag is checked
(:func:`check_bag`) and deleted.
"""
from __future__ import annotations

import json
import os
import shutil
import threading
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from baglib.read.metadata_read import load_metadata
from baglib.read.reader import BagReader
from baglib.read.storage_reader import BagReadError
from benchmarks.endurance.accounting import Union
from benchmarks.endurance.bag_files import FileContent, read_file
from benchmarks.record.modes import RecorderServices


@dataclass
class FileRecord:
    """What the soak keeps of one read file: its counts (for the bag check) and the readers' figures."""

    messages: int
    size: int
    counts: dict[str, int]
    rosbags_read: int
    seconds: float
    cpu_s: float
    heads_only: bool


@dataclass
class RecorderRun:
    """One recorder of the soak, from its load to its bag's check."""

    index: int
    name: str
    bag: Path
    unique_id: int
    services: RecorderServices
    loaded_at: float
    lost_events: list[str] = field(default_factory=list)  # messages_lost events, as text
    pending: dict[str, tuple[Future, Path]] = field(default_factory=dict)  # file name -> (worker's read, link)
    files: dict[str, FileRecord] = field(default_factory=dict)  # file name -> what its reading found
    final: Optional[dict[str, Any]] = None  # ~/stop_recording's final counts
    stopping: Any = None  # the pending ~/stop_recording call (an rclpy Future)
    unloaded: bool = False
    check: Optional[dict[str, Any]] = None

    def on_lost_event(self, event: Any) -> None:
        self.lost_events.append("; ".join(f"{s.topic_name}: transport {s.messages_lost_in_transport}, "
                                          f"recorder {s.messages_lost_in_recorder}"
                                          for s in event.messages_lost_statistics))

    def collect(self, links: Path, pool: Executor, problems: list[str]) -> None:
        """Hand every file ``metadata.yaml`` newly lists to the worker, through a hard link."""
        try:
            listed = [info.path for info in load_metadata(self.bag).files]
        except BagReadError:
            return  # nothing finished yet
        for name in listed:
            if name in self.pending or name in self.files:
                continue
            link = links / f"{self.name}__{Path(name).name}"
            try:
                os.link(self.bag / name, link)
            except FileNotFoundError:
                problems.append(f"{self.name}: {name} was deleted before it could be read")
                continue
            self.pending[name] = (pool.submit(read_file, str(link)), link)

    def harvest(self, union: Union, problems: list[str]) -> list[FileContent]:
        """Take in every file the worker has read: into the union, its link removed."""
        done = []
        for name, (future, link) in list(self.pending.items()):
            if not future.done():
                continue
            del self.pending[name]
            link.unlink(missing_ok=True)
            try:
                content = future.result()
            except Exception as exc:  # noqa: BLE001 - a file a reader cannot read is the finding
                problems.append(f"{self.name}: {name} could not be read: {type(exc).__name__}: {exc}")
                continue
            union.add(self.index, content)
            problems.extend(f"{self.name}: {name}: {problem}" for problem in content.problems)
            self.files[name] = FileRecord(content.messages, content.size, content.counts,
                                          sum(content.rosbags_read.values()), content.seconds, content.cpu_s,
                                          content.heads_only)
            done.append(content)
        return done

    def ready_for_check(self) -> bool:
        return self.unloaded and self.check is None and not self.pending

    def finish(self, stop_reply: Any) -> None:
        """``~/stop_recording``'s reply: the final counts (or the failure)."""
        message = stop_reply.message
        self.final = json.loads(message) if message.startswith("{") else {"error": message}


class Collector:
    """A thread that hands every recorder's newly finished files to the worker every ``period`` seconds, so that
    no call the churn waits on (a recorder finishing a backlog can take many seconds) holds it up: circular
    recording deletes a file a few splits after listing it. ``lock`` guards the recorders' pending files."""

    def __init__(self, links: Path, pool: Executor, period: float, problems: list[str]) -> None:
        self.links, self.pool, self.period, self.problems = links, pool, period, problems
        self.recorders: list[RecorderRun] = []
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="soak_file_collector", daemon=True)
        self._thread.start()

    def collect(self) -> None:
        with self.lock:
            for recorder in self.recorders:
                if recorder.check is None:
                    recorder.collect(self.links, self.pool, self.problems)

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self.collect()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def written_problems(recorder: RecorderRun) -> list[str]:
    """The recorder's final counts against the files: written per topic as read, nothing dropped, no error."""
    final = recorder.final or {}
    problems = []
    if final.get("error") or final.get("serialize_errors"):
        problems.append(f"recorder error: {final.get('error')}, serialize errors {final.get('serialize_errors')}")
    read: dict[str, int] = {}
    for record in recorder.files.values():
        for topic, count in record.counts.items():
            read[topic] = read.get(topic, 0) + count
    written = {topic: c["written"] for topic, c in (final.get("topics") or {}).items() if c["written"]}
    if written != read:
        problems.append(f"written per topic (recorder) {written} != read from its files {read}")
    deleted = {Path(path).name for path in final.get("deleted_files", [])}
    if not deleted <= set(recorder.files):
        problems.append(f"deleted before read: {sorted(deleted - set(recorder.files))}")
    return problems


def check_bag(recorder: RecorderRun) -> dict[str, Any]:
    """Is the bag finalized (metadata.yaml naming exactly the files left, with their counts) and readable as a
    whole by both readers; do the recorder's final counts match what its files hold; did it drop anything."""
    from rosbags.rosbag2 import Reader
    problems = written_problems(recorder)
    final = recorder.final or {}
    drops = sum(c.get("dropped", 0) + c.get("queue_dropped", 0) for c in (final.get("topics") or {}).values())
    try:
        metadata = load_metadata(recorder.bag)
        listed = sorted(info.path for info in metadata.files)
        on_disk = sorted(path.name for path in recorder.bag.glob("*.mcap"))
        if listed != on_disk:
            problems.append(f"metadata.yaml lists {listed}, the directory holds {on_disk}")
        for info in metadata.files:
            record = recorder.files.get(info.path)
            if record is None or record.messages != info.message_count:
                problems.append(f"{info.path}: metadata.yaml says {info.message_count} messages, read "
                                f"{None if record is None else record.messages}")
        with BagReader(recorder.bag) as bag, Reader(recorder.bag) as reader:
            if not bag.message_count == reader.message_count == metadata.message_count:
                problems.append(f"bag message count: baglib {bag.message_count}, rosbags {reader.message_count}, "
                                f"metadata {metadata.message_count}")
    except Exception as exc:  # noqa: BLE001 - an unreadable bag is the finding
        problems.append(f"bag not readable as a whole: {type(exc).__name__}: {exc}")
    return {"name": recorder.name, "files": len(recorder.files), "messages": sum(r.messages for r in
                                                                                 recorder.files.values()),
            "bytes": sum(r.size for r in recorder.files.values()), "dropped": drops,
            "lost_events": recorder.lost_events, "peak_backlog_bytes": final.get("peak_backlog_bytes"),
            "problems": problems}


def discard(recorder: RecorderRun, keep: bool) -> None:
    if not keep:
        shutil.rmtree(recorder.bag, ignore_errors=True)
