"""One bag being recorded: the write path from the intake cache to the files.

The session owns a :class:`BagWriter`, the :class:`MessageCache` the intake fills, and the writer thread
that serializes intra-process message objects (DDS payloads already are CDR bytes) and writes them. Nothing
here runs on the executor except :meth:`offer`, which only appends to the cache.

A storage failure (disk full, file removed) ends the session: the error is kept and logged, the bag is
closed with what was written, and further messages are counted as dropped. ``finish`` is idempotent.
"""
from __future__ import annotations

import threading
import time
from collections import Counter, deque
from typing import Any, Callable

from components.recorder import cdr_fast
from components.recorder.cdr_fast import CdrData
from components.recorder.bag_writer import BagWriteError, BagWriter
from components.recorder.message_cache import CachedMessage, MessageCache, payload_size
from components.recorder.metadata import TopicInfo
from components.recorder.recorder_options import RecordOptions

Serializer = Callable[[Any], CdrData]
#: Per topic, messages lost before the intake during this session (the subscriptions' queue overflows).
QueueDrops = Callable[[], dict[str, int]]
LATENCY_SAMPLES = 20_000


def _percentiles(samples_ns: list[int]) -> dict[str, float] | None:
    """p50/p99 in milliseconds of the receive-to-write latencies, None before the first write."""
    if not samples_ns:
        return None
    ordered = sorted(samples_ns)
    return {q: ordered[min(len(ordered) - 1, int(len(ordered) * f))] / 1e6
            for q, f in (("p50", 0.50), ("p99", 0.99))}


class RecordingSession:
    """Records into one bag directory until :meth:`finish`."""

    def __init__(self, options: RecordOptions, uri: str, logger: Any,
                 on_split: Callable[[str, str], None] | None = None,
                 serialize: Serializer = cdr_fast.serialize, queue_drops: QueueDrops | None = None) -> None:
        self._logger = logger
        self._serialize = serialize
        self._queue_drops = queue_drops
        self._last_log_time = 0
        self._monotonic_log_times = options.storage_preset_profile == "fastwrite"
        self.writer = BagWriter(uri, options.storage_id, options.max_bagfile_size,
                                options.max_bagfile_duration, options.storage_preset_profile,
                                options.custom_data or None, on_split)
        self.cache = MessageCache(options.max_cache_size, ring=options.snapshot_mode)
        self.write_dropped: Counter[str] = Counter()
        # Messages the writer accepted; after a storage failure the file may hold fewer (a buffered chunk that
        # could not reach the disk), and the difference is lost too.
        self.handed: Counter[str] = Counter()
        self.error: str | None = None
        # receive-to-write latencies (ns) of the most recent messages, for the stats and the benchmark
        self._latencies: deque[int] = deque(maxlen=LATENCY_SAMPLES)
        self._snapshot_mode = options.snapshot_mode
        self._snapshot_requested = threading.Event()
        self._snapshots: deque[list[CachedMessage]] = deque()  # taken from the ring, waiting to be written
        self._finish_lock = threading.Lock()
        self._finished = False
        self._thread = threading.Thread(target=self._run, name=f"bag_writer:{self.writer.path.name}",
                                        daemon=True)
        self._thread.start()

    @property
    def active(self) -> bool:
        return not self._finished and self.error is None

    def add_topic(self, info: TopicInfo) -> None:
        """Declare a topic in the bag (listed even if it never gets a message)."""
        try:
            self.writer.add_topic(info)
        except BagWriteError as exc:
            self._fail(exc)

    def offer(self, topic: str, payload: Any, log_time_ns: int, publish_time_ns: int) -> None:
        """Intake: hand one message to the writer thread. Never blocks on I/O."""
        self.cache.push(CachedMessage(topic, payload, payload_size(payload), log_time_ns, publish_time_ns))

    def snapshot(self) -> bool:
        """Snapshot mode: write what the ring cache holds now. False outside snapshot mode or when failed."""
        if not self._snapshot_mode or not self.active:
            return False
        self._snapshots.append(self.cache.drain())  # the ring as it is now, not when the writer wakes
        self._snapshot_requested.set()
        return True

    def split(self) -> bool:
        if not self.active:
            return False
        try:
            self.writer.split()
        except BagWriteError as exc:
            self._fail(exc)
            return False
        return True

    # --- writer thread ----------------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            if self._snapshot_mode:
                self._snapshot_requested.wait(0.2)
                self._snapshot_requested.clear()
                batch = self._snapshots.popleft() if self._snapshots else []
            else:
                batch = self.cache.take_all(timeout=0.2)
            batch.sort(key=_log_time)  # stable: each topic keeps its order
            for index, message in enumerate(batch):
                if not self._write(message):
                    for lost in batch[index:]:
                        self.write_dropped[lost.topic] += 1
                    return
            if self.cache.closed and not batch:
                return

    def _write(self, message: CachedMessage) -> bool:
        payload = message.payload
        data = payload if isinstance(payload, (bytes, bytearray, memoryview)) else self._serialize(payload)
        message.payload = None  # let the message object go as soon as it is serialized
        # Unindexed MCAP files (fastwrite) must have ascending log times: their readers, rosbags among them,
        # refuse files where they do not. There, a message that reached the intake after a newer one was
        # written (another topic's queue was served first) is stamped with that newer time.
        log_time = message.log_time_ns
        if self._monotonic_log_times:
            log_time = self._last_log_time = max(log_time, self._last_log_time)
        try:
            self.writer.write(message.topic, data, log_time, message.publish_time_ns)
            self.handed[message.topic] += 1
            self._latencies.append(time.time_ns() - message.log_time_ns)
        except BagWriteError as exc:
            self._fail(exc)
            return False
        finally:
            self.cache.release(message)
        return True

    def _fail(self, exc: BagWriteError) -> None:
        if self.error is None:
            self.error = str(exc)
            self._logger.error(f"Recording to {self.writer.path} stopped: {exc}. The bag holds what was written "
                               "before the failure; later messages are counted as dropped.")
        self.cache.close()

    # --- end --------------------------------------------------------------------------------------------
    def finish(self) -> None:
        """Flush the cache, close the bag (summary, metadata.yaml) and log the counts. Idempotent."""
        with self._finish_lock:
            if self._finished:
                return
            self._finished = True
        if self._snapshot_mode:
            for message in self.cache.drain():  # a ring that was never snapshotted is simply discarded
                self.cache.release(message)
        self.cache.close()
        self._thread.join()
        for message in self.cache.drain():  # left behind by a failed writer: counted, not written
            self.write_dropped[message.topic] += 1
        try:
            self.writer.close()
        except BagWriteError as exc:
            self._fail(exc)
        self._logger.info(self.summary())

    def stats(self) -> dict[str, Any]:
        """Live counts per topic, for the ``~/get_stats`` service and the closing log line."""
        written = self.writer.topic_message_counts
        queue = Counter(self._queue_drops() if self._queue_drops else {})
        topics = sorted(set(written) | set(self.cache.received) | set(queue))
        # Only a failure loses accepted messages (the writer thread has stopped then, so the counts are still).
        lost_in_storage = Counter({t: n - written.get(t, 0) for t, n in self.handed.items()} if self.error else {})
        dropped = self.cache.dropped + self.write_dropped + queue + lost_in_storage
        return {
            "bag": str(self.writer.path),
            "current_file": str(self.writer.current_file or ""),
            "bytes_written": self.writer.bytes_written,
            "cache_bytes": self.cache.bytes,
            "error": self.error,
            "write_latency_ms": _percentiles(list(self._latencies)),
            "topics": {t: {"received": self.cache.received[t], "written": written.get(t, 0),
                           "dropped": dropped[t], "queue_dropped": queue[t]} for t in topics},
        }

    def summary(self) -> str:
        stats = self.stats()
        lines = [f"Bag {stats['bag']} closed: {sum(t['written'] for t in stats['topics'].values())} messages, "
                 f"{stats['bytes_written']} bytes" + (f", error: {stats['error']}" if stats["error"] else "")]
        for topic, counts in stats["topics"].items():
            lines.append(f"  {topic}: received {counts['received']}, written {counts['written']}, "
                         f"dropped {counts['dropped']}")
        return "\n".join(lines)


def _log_time(message: CachedMessage) -> int:
    return message.log_time_ns
