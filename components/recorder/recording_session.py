"""One bag being recorded: the write path from the intake cache to the files.

The session owns a :class:`BagWriter`, the :class:`MessageCache` the intake fills, and the writer thread
that serializes intra-process message objects (DDS payloads already are CDR bytes) and writes them. Nothing
here runs on the executor except :meth:`offer`, which only appends to the cache.

The writer thread is supervised, so one bad message or one bad disk never silently ends a recording:

* a message object that cannot be serialized (field checks are off by default in Jazzy, so a malformed
  message reaches the recorder) is dropped and counted with its reason; the recording goes on;
* a storage failure (disk full, file removed), and anything else the writer thread did not expect, ends the
  session: the error is kept and logged, the bag is closed with what was written, and further messages are
  counted as dropped;
* snapshot mode holds at most one snapshot waiting for the writer: another ``~/snapshot`` meanwhile is refused,
  so requests cannot queue copies of the ring without bound (memory stays within twice ``max_cache_size``:
  the ring refilling plus the snapshot being written); a snapshot taken is always written, even when the
  session finishes right after, and one that cannot be written any more is refused;
* :meth:`finish` is bounded: a writer that does not finish in time (a hung disk) is abandoned, its bag left
  unfinalized (repairable) and the error recorded.

Every drop is counted per topic and reason (``drop_reasons`` in :meth:`stats`), ``awaiting_keyframe`` among
them (with ``record.compress`` to video, files begin each video topic at a keyframe: keyframe_gate).
``finish`` is idempotent.
Messages that ``record.max_rates`` leaves out are not drops: they are counted apart, as ``rate_limited`` per topic
and in ``dropped_by_design`` (a bag holds what was asked for; ``dropped`` and ``drop_reasons`` are losses).

A topic an ImageEncoder of the container publishes (recorded compressed) also accounts for the raw frames the
encoder received while the bag was open (:meth:`RecordingSession.account_encoder`): those it lost are drops of the
topic (``encoder_behind``, ``encoder_rejected``, ``encoder_stopped``), its ``received`` counts raw frames, and
``written`` + ``dropped`` + ``rate_limited`` = ``received`` still holds. ``record.max_rates`` on a topic of the
recorder's own encoder thins the encoder's input, so every recorded access unit decodes; on a video topic of
another encoder it is not applied (it would break decoding; the recorder warns). The bag keeps each such
account in ``metadata.yaml`` (baglib/format/frame_accounts.py).

Latched topics (``record.repeat_transient_local``): the writer starts every split file with their last messages
(BagWriter.repeat_topic), and every snapshot starts with those the ring no longer holds, stamped with the receive
and publish times of the snapshot's first message, as rosbag2 Rolling does. Those copies are counted per topic as
``repeated``, never as ``written``: per topic, ``received`` = ``written`` + ``dropped`` + ``rate_limited`` still.
"""
from __future__ import annotations

import threading
import time
import traceback
from collections import Counter, defaultdict, deque
from dataclasses import dataclass
from typing import Any, Callable

from baglib.format import cdr_fast, frame_accounts
from baglib.format.cdr_fast import CdrData
from baglib.write.direct_file import GATHER
from baglib.write.writer import BagWriteError, BagWriter
from component_container.process_tuning import release_free_memory, resident_bytes
from components.recorder.disk_guard import DiskGuard
from components.recorder.keyframe_gate import AWAITING_KEYFRAME, KeyframeGate, Verdict, VideoTopics
from components.recorder.loss_events import ENCODER_LOSSES
from components.recorder.message_cache import CachedMessage, MessageCache, payload_size
from components.recorder.rate_limits import RATE_LIMITED, RateLimiter, parse_max_rates
from baglib.format.metadata import TopicInfo
from components.recorder.recorder_options import RecordOptions

Serializer = Callable[[Any], CdrData]
#: Per topic, messages lost before the intake during this session (the subscriptions' queue overflows).
QueueDrops = Callable[[], dict[str, int]]
LATENCY_SAMPLES = 20_000
#: Longest the writer thread sleeps without new messages (it then checks the flush and sync deadlines).
WAKE_PERIOD = 0.2
#: Longest the writer lets messages gather into one batch (MessageCache.take_all), at most half a wake period.
#: Every batch hands the GIL between the executor and the writer and back; at ten thousand Imu messages a
#: second, 20 ms instead of 5 cuts the CPU per message by about an eighth, at ~13 ms median write latency.
BATCH_GATHER = 0.02
#: The writer frees the cache room of small messages it wrote this many bytes at a time (and after each batch).
RELEASE_STEP = 1 << 20
#: How often the writer thread checks the free disk space and the bag file (statvfs + stat: microseconds).
DISK_CHECK_PERIOD = 0.05

# Why a message was dropped: the keys of ``drop_reasons`` in the stats.
CACHE_FULL = "cache_full"                # the cache was full: the writer fell behind
QUEUE_FULL = "queue_full"                # a subscription's queue overflowed before the intake
SERIALIZE_FAILED = "serialize_failed"    # the message object could not be serialized
STORAGE_FAILED = "storage_failed"        # taken in (or arriving) after the storage failed or hung, never written
RECORDING_STOPPED = "recording_stopped"  # received inside the window, but reached the intake after its bag closed
#: The key of ``custom_data`` in a bag's metadata that lists its ``record.max_rates``.
MAX_RATES_KEY = "record.max_rates"
_ENCODER_COUNTS = ("received", "published", *ENCODER_LOSSES)


def _percentiles(samples_ns: list[int]) -> dict[str, float] | None:
    """p50/p99 in milliseconds of the receive-to-write latencies, None before the first write."""
    if not samples_ns:
        return None
    ordered = sorted(samples_ns)
    return {q: ordered[min(len(ordered) - 1, int(len(ordered) * f))] / 1e6
            for q, f in (("p50", 0.50), ("p99", 0.99))}


def _describe(exc: BaseException) -> str:
    """A storage error as the OS put it; anything else with its type, since it is a bug to report."""
    return str(exc) if isinstance(exc, BagWriteError) else f"unexpected {type(exc).__name__}: {exc}"


class RecordingSession:
    """Records into one bag directory until :meth:`finish`."""

    def __init__(self, options: RecordOptions, uri: str, logger: Any,
                 on_split: Callable[[str, str], None] | None = None,
                 serialize: Serializer = cdr_fast.serialize, queue_drops: QueueDrops | None = None,
                 writer_class: type[BagWriter] = BagWriter, video: VideoTopics | None = None) -> None:
        self._logger = logger
        # Video topics: each file begins each of them at a keyframe (keyframe_gate); the messages held for the file
        # a pending split opens (the writer thread's). With encoders in the container (intra-process) from the
        # start; otherwise from the first video topic, so that a bag without video splits as the writer says.
        self._video = video
        self.gate = KeyframeGate(video) if video is not None and video.in_process else None
        self._held: list[CachedMessage] = []
        self._split_next = False
        self._serialize = serialize
        self._queue_drops = queue_drops
        self._last_log_time = 0
        self._monotonic_log_times = options.storage_preset_profile == "fastwrite"
        self._rate_limiter = RateLimiter(parse_max_rates(options.max_rates)) if options.max_rates else None
        custom_data = dict(options.custom_data)
        if options.max_rates:  # the bag says what it holds: metadata.yaml's custom_data names the limits
            custom_data.setdefault(MAX_RATES_KEY, ", ".join(options.max_rates))
        self.writer = writer_class(uri, options.storage_id, options.max_bagfile_size,
                                   options.max_bagfile_duration, options.storage_preset_profile,
                                   custom_data or None, on_split, options.max_bag_files,
                                   gather_bytes=GATHER)
        try:  # after the writer: a location that cannot hold a bag at all is reported as such first
            self.disk = DiskGuard(self.writer.path, options.min_free_space)
        except ValueError:
            self.writer.discard()
            raise
        self._next_disk_check = 0.0
        self._written_unreleased = 0  # bytes of messages written but still counted in the cache
        self.cache = MessageCache(options.max_cache_size, ring=options.snapshot_mode, reserve=options.stall_reserve,
                                  max_duration=options.max_cache_duration)
        # Snapshot mode: per latched topic, its last messages as received (the ring may have evicted them)
        self._latched: dict[str, deque[CachedMessage]] = {}
        # The live counts are the session's own, not the writer's: reading the writer's would wait on its lock,
        # which a write to a hung disk holds forever (and ~/get_stats, health and unload must still answer).
        self._topics: set[str] = set()
        # Messages the writer accepted; after a storage failure the file may hold fewer (a buffered chunk that
        # could not reach the disk), and the difference is lost too.
        self.handed: Counter[str] = Counter()
        self._bytes_written = 0  # the writer's count after its latest batch
        self._stats_lock = threading.Lock()  # the writer thread's drop counts and errors, read by others
        self._writer_drops: defaultdict[str, Counter[str]] = defaultdict(Counter)
        self._missed: Counter[str] = Counter()  # see missed()
        # Per topic an in-container encoder publishes: its stream and counts when the bag began taking the topic;
        # the deltas are frozen when the bag is finished (account_encoder)
        self._encoders: dict[str, tuple[Any, dict[str, int]]] = {}
        self._encoder_final: dict[str, dict[str, int]] | None = None
        self._not_limited: set[str] = set()  # topics record.max_rates matches that offer() does not limit
        self.serialize_errors: dict[str, str] = {}  # per topic, the first reason a message could not be serialized
        self.error: str | None = None
        # receive-to-write latencies (ns) of the most recent messages, for the stats and the benchmark
        self._latencies: deque[int] = deque(maxlen=LATENCY_SAMPLES)
        self._snapshot_mode = options.snapshot_mode
        # Backlogs that went into the stall reserve and whose memory went back to the system (_return_memory).
        self._reserve_entries_returned = 0
        self.memory_returns = 0
        self.memory_returned_bytes = 0
        # Loss bounds: flush/sync deadlines, checked after every batch and at least every wake-up period.
        self._flush_ns = round(options.flush_interval * 1e9)
        self._sync_ns = round(options.sync_interval * 1e9)
        self._wake_ns = round(min(WAKE_PERIOD, (options.flush_interval or WAKE_PERIOD) / 4) * 1e9)
        self._oldest_unflushed_ns: int | None = None
        self._last_sync_ns = time.time_ns()
        self._unsynced = False
        self._snapshot_requested = threading.Event()
        # Taken from the ring and not yet written; guarded by _finish_lock, so that a snapshot is never taken
        # once finish() has begun (the writer then would not be waiting for it any more).
        self._snapshot: list[CachedMessage] | None = None
        self._finish_lock = threading.Lock()
        self._finished = False
        # finish() gave up waiting for the writer (a stalled disk): the writer closes the bag itself if it ever
        # gets to its end; ``_writer_done`` says it got there first. Both under ``_abandon_lock``.
        self._abandon_lock = threading.Lock()
        self._abandoned = False
        self._writer_done = False
        self._on_late_close: Callable[[], None] | None = None
        self._closed_late = False
        # A daemon: a writer stuck on a hung disk is abandoned by finish() and must not keep the process alive.
        self._thread = threading.Thread(target=self._run, name=f"bag_writer:{self.writer.path.name}",
                                        daemon=True)
        self._thread.start()

    @property
    def active(self) -> bool:
        return not self._finished and self.error is None

    @property
    def writing_after_finish(self) -> bool:
        """finish() gave up on the writer and it has not got to its end yet (its counts may still change)."""
        with self._abandon_lock:
            return self._abandoned and not self._writer_done

    def add_topic(self, info: TopicInfo, repeat_depth: int = 0) -> None:
        """Declare a topic in the bag (listed even if it never gets a message); with ``repeat_depth``, its last
        messages start every split file and every snapshot (see the module docstring).

        Raises what BagWriter.add_topic raises for a topic it cannot describe (no definition installed); a
        storage failure instead ends the session.
        """
        try:
            self.writer.add_topic(info)
            if repeat_depth:
                self.writer.repeat_topic(info.name, repeat_depth)
        except BagWriteError as exc:
            self._fail(exc)
        if repeat_depth and self._snapshot_mode:
            self._latched[info.name] = deque(self._latched.get(info.name, ()), maxlen=repeat_depth)
        if self.gate is None and self._video is not None and info.name in self._video:
            self.gate = KeyframeGate(self._video)  # before the topic's first message can reach the writer
        self._topics.add(info.name)

    def account_encoder(self, topic: str, stream: Any, owned: bool) -> str | None:
        """``topic`` is published by an encoder stream of this container: the bag accounts for the raw frames it
        receives from now on (module docstring). ``owned``: the recorder's own encoder, whose input a rate limit
        on ``topic`` thins (:meth:`admits_raw`). A warning to log, if any."""
        with self._stats_lock:
            self._encoders[topic] = (stream, stream.stats())
        if self._rate_limiter is None or not self._rate_limiter.limits(topic):
            return None
        if owned:
            self._not_limited.add(topic)  # limited before the encoder instead (admits_raw)
            return None
        if stream.is_video:
            self._not_limited.add(topic)
            return (f"record.max_rates: not applied to {topic}, the video of an encoder the recorder did not load: "
                    "leaving out access units would break decoding until the next keyframe (record it with "
                    "record.compress to thin the encoder's input instead)")
        return None

    def admits_raw(self, topic: str) -> bool:
        """For the recorder's own encoder of ``topic``: whether the raw frame it is offered now is encoded
        (``record.max_rates``; left out, it is counted as rate_limited here)."""
        return self._rate_limiter is None or self._rate_limiter.admits(topic, time.time_ns())

    def offer(self, topic: str, payload: Any, log_time_ns: int, publish_time_ns: int) -> bool | None:
        """Intake: hand one message to the writer thread. Never blocks on I/O, never raises. True: taken;
        False: dropped or rate limited, and counted; None: offered after the bag's cut point (see
        MessageCache.push)."""
        if self._rate_limiter is not None and not self.cache.closed and topic not in self._not_limited and \
                not self._rate_limiter.admits(topic, log_time_ns):
            return False
        size = payload_size(payload)
        taken = self.cache.push(CachedMessage(topic, payload, size, log_time_ns, publish_time_ns))
        latched = self._latched.get(topic)
        if taken and latched is not None:  # its own record: the writer lets go of the ring's once written
            latched.append(CachedMessage(topic, payload, size, log_time_ns, publish_time_ns))
        return taken

    def missed(self, topic: str) -> None:
        """A message received inside this bag's window reached the intake after the bag was closed (a busy
        executor took it late): received, and dropped as ``recording_stopped``."""
        with self._stats_lock:
            self._missed[topic] += 1

    def snapshot(self) -> str | None:
        """Snapshot mode: write what the ring cache holds now. None when taken, else why it was refused.

        Refused outside snapshot mode, once the session is finishing or failed (the snapshot would be lost),
        and while the previous snapshot is still being written (see the module docstring).
        """
        if not self._snapshot_mode:
            return "not in snapshot mode (storage.snapshot_mode is false)"
        with self._finish_lock:
            if self._finished or self.error is not None:
                return "the bag is finishing or has failed"
            if self._snapshot is not None:
                return "the previous snapshot is still being written"
            self._snapshot = self._with_latched(self.cache.drain())  # the ring as it is now, not when the writer wakes
        self._snapshot_requested.set()
        return None

    def _with_latched(self, ring: list[CachedMessage]) -> list[CachedMessage]:
        """A snapshot: the ring, after the latched messages it no longer holds, stamped with the receive and
        publish times of its first message (rosbag2 Rolling's ``--repeat-transient-local``); those still in the
        ring are in it already. With an empty ring they keep their own times."""
        first = min(ring, key=_log_time, default=None)
        kept = sorted((m for latched in self._latched.values() for m in list(latched)
                       if first is None or m.log_time_ns < first.log_time_ns), key=_log_time)
        if first is None:
            return [CachedMessage(m.topic, m.payload, m.size, m.log_time_ns, m.publish_time_ns, repeat=True)
                    for m in kept]
        return [CachedMessage(m.topic, m.payload, m.size, first.log_time_ns, first.publish_time_ns, repeat=True)
                for m in kept] + ring

    def split(self) -> bool:
        """Close the current file and go on in the next; with compressed video, at its next keyframe."""
        if not self.active:
            return False
        if self.gate is not None:
            self.gate.split()
            return True
        try:
            self.writer.split()
        except BagWriteError as exc:
            self._fail(exc)
            return False
        except ValueError:  # the writer thread closed the bag after a failure meanwhile
            return False
        return True

    # --- writer thread ----------------------------------------------------------------------------------
    def _run(self) -> None:
        """Write batches until the cache is closed and empty; never dies silently (see module docstring)."""
        batch: list[CachedMessage] = []
        written = 0
        try:
            while True:
                # Read before taking: whatever was handed over before the close is in this batch or a later one.
                closed = self.cache.closed
                batch, written = self._next_batch(), 0
                batch.sort(key=_log_time)  # stable: each topic keeps its order
                for message in batch:
                    self._write(message)
                    written += 1
                if batch:
                    self.writer.write_gathered()
                self._release_written()
                self._bytes_written = self.writer.bytes_written
                self._check_storage()
                self._keep_loss_bounds()
                self._return_memory()
                if self._snapshot is batch:
                    self._snapshot = None  # written: the next snapshot may be taken
                if closed and not batch:
                    self._write_held()
                    break
        except Exception as exc:  # noqa: BLE001 - whatever it is, it ends the session as a storage failure
            self._fail(exc)
            self._release_written()
            self._discard(batch[written:], STORAGE_FAILED)
            self._close_writer()  # the bag is finalized now, not only at unload
        self._end_of_writing()

    def _end_of_writing(self) -> None:
        """The writer thread's last step: if finish() gave up on it meanwhile, the bag is still closed now
        (summary, metadata.yaml: readable without a repair), its file descriptors released, and whoever kept
        the final counts is told that they changed (what the writer wrote after all)."""
        with self._abandon_lock:
            self._writer_done = True
            late, on_late_close = self._abandoned, self._on_late_close
        if late:
            self._close_writer()
            self._closed_late = True  # the writer's lock is free for good: its counts may be read
            self._logger.warning(f"Recording to {self.writer.path}: the writer finished after all; the bag is "
                                 "closed with what it wrote")
            if on_late_close is not None:
                on_late_close()

    def _check_storage(self) -> None:
        """At most every DISK_CHECK_PERIOD: the free-space guard, and whether the bag file is still ours on
        disk (deleted or replaced files are storage failures). Both raise BagWriteError, ending the session."""
        now = time.monotonic()
        if now < self._next_disk_check:
            return
        self._next_disk_check = now + DISK_CHECK_PERIOD
        self.disk.check(self._bytes_written)
        self.writer.check_files()

    def _keep_loss_bounds(self) -> None:
        """The two promises of docs/recorder.md, "Crash and power-loss guarantees": a message received more than
        ``flush_interval`` ago is a complete record in the file (handed to the OS), and what was written more
        than ``sync_interval`` ago is on the disk. Flushing starts one wake-up early so the bound holds."""
        now = time.time_ns()
        oldest = self._oldest_unflushed_ns
        if self._flush_ns and oldest is not None and now - oldest >= self._flush_ns - self._wake_ns:
            self.writer.flush()
            self._oldest_unflushed_ns = None
        if self._sync_ns and self._unsynced and now - self._last_sync_ns >= self._sync_ns:
            self.writer.sync()
            self._last_sync_ns, self._unsynced = now, False

    def _return_memory(self) -> None:
        """Once a backlog that went into the stall reserve has drained (the cache holds at most a quarter of
        ``max_cache_size`` again), give the memory its messages held back to the system, once per such backlog.
        glibc keeps freed heap memory for reuse: without this the container would keep a stall's backlog, up to
        the whole reserve, as resident memory for good."""
        entries = self.cache.reserve_entries
        if entries == self._reserve_entries_returned or self.cache.bytes > self.cache.max_bytes // 4:
            return
        self._reserve_entries_returned = entries
        before = resident_bytes()
        if release_free_memory():
            self.memory_returns += 1
            returned = max(0, before - resident_bytes())
            self.memory_returned_bytes += returned
            self._logger.info(f"The backlog has drained: {returned / 1e6:.0f} MB of memory returned to the system")

    def _next_batch(self) -> list[CachedMessage]:
        wake = self._wake_ns / 1e9
        if not self._snapshot_mode:
            return self.cache.take_all(timeout=wake, gather=min(BATCH_GATHER, wake / 2))
        self._snapshot_requested.wait(wake)
        self._snapshot_requested.clear()
        return self._snapshot if self._snapshot is not None else []  # pending until written

    def _write(self, message: CachedMessage) -> None:
        """Write one message, where the keyframe gate says (keyframe_gate); raises what the storage raised (the
        caller ends the session)."""
        if self.gate is None:
            self._put(message)
            return
        verdict, split = self.gate.admit(message.topic, message.payload, message.log_time_ns,
                                         self.writer.split_due(message.log_time_ns))
        self._split_next = self._split_next or split
        if verdict is Verdict.HOLD:
            self._held.append(message)
        if split:  # the held messages begin the new file
            held, self._held = self._held, []
            for kept in held:
                self._put(kept)
        if verdict is Verdict.WRITE:
            self._put(message)
        elif verdict is Verdict.DROP:
            self._discard([message], AWAITING_KEYFRAME)

    def _put(self, message: CachedMessage) -> None:
        """Serialize and write one message; with the gate, in the current file or (a split due) the next."""
        split: bool | None = None
        if self.gate is not None:
            split, self._split_next = self._split_next, False
        payload = message.payload
        try:
            data = payload if isinstance(payload, (bytes, bytearray, memoryview)) else self._serialize(payload)
        except Exception as exc:  # noqa: BLE001 - a malformed message object: dropped, the recording goes on
            self._split_next = bool(split)  # a split due still happens before the next message written
            self._drop_unserializable(message, exc)
            return
        message.payload = None  # let the message object go as soon as it is serialized
        # Unindexed MCAP files (fastwrite) must have ascending log times: their readers, rosbags among them,
        # refuse files where they do not. There, a message that reached the intake after a newer one was
        # written (another topic's queue was served first) is stamped with that newer time.
        log_time = message.log_time_ns
        if self._monotonic_log_times:
            log_time = self._last_log_time = max(log_time, self._last_log_time)
        if message.repeat:
            self.writer.write(message.topic, data, log_time, message.publish_time_ns, split, repeat=True)
        else:
            self.writer.write(message.topic, data, log_time, message.publish_time_ns, split)
        if self._oldest_unflushed_ns is None:
            self._oldest_unflushed_ns = message.log_time_ns  # the receive time
        self._unsynced = True
        if message.repeat:
            return
        self.handed[message.topic] += 1
        self._latencies.append(time.time_ns() - message.log_time_ns)
        self._written_unreleased += message.size
        if self._written_unreleased >= RELEASE_STEP:
            self._release_written()

    def _write_held(self) -> None:
        """The bag closes during a split: what was held for the next file ends the current one (each held
        topic continues there from its keyframe)."""
        held, self._held, self._split_next = self._held, [], False
        for message in held:
            self._put(message)
        if held:
            self.writer.write_gathered()
            self._release_written()

    def _release_written(self) -> None:
        """Free the room of the messages written so far (a lock shared with the intake: not per small one)."""
        self.cache.release(self._written_unreleased)
        self._written_unreleased = 0

    def _drop_unserializable(self, message: CachedMessage, exc: Exception) -> None:
        reason = f"{type(exc).__name__}: {exc}"
        with self._stats_lock:
            self._writer_drops[message.topic][SERIALIZE_FAILED] += 1
            first = self.serialize_errors.setdefault(message.topic, reason) is reason
        self.cache.release(message.size)
        if first:  # once per topic: a publisher that keeps sending broken messages must not flood the log
            self._logger.error(f"Dropped a message on {message.topic} that cannot be serialized ({reason}); "
                               "recording goes on, further failures on this topic are counted in ~/get_stats")

    def _discard(self, messages: list[CachedMessage], reason: str) -> None:
        """Count messages that will never be written, and free their room in the cache."""
        with self._stats_lock:
            for message in messages:
                self._writer_drops[message.topic][reason] += 1
        self.cache.release(sum(message.size for message in messages))

    def _fail(self, exc: BaseException | str) -> None:
        """End the session: keep and log the first error; the cache refuses everything from now on."""
        reason = exc if isinstance(exc, str) else _describe(exc)
        with self._stats_lock:
            first, self.error = self.error is None, self.error or reason
        if not first:
            self._logger.warning(f"Recording to {self.writer.path}, after the failure: {reason}")
        elif isinstance(exc, (str, BagWriteError)):
            self._logger.error(f"Recording to {self.writer.path} stopped: {reason}. The bag holds what was "
                               "written before the failure; later messages are counted as dropped.")
        else:
            self._logger.error(f"Recording to {self.writer.path} stopped: {reason}. The bag is closed with what "
                               "was written; later messages are counted as dropped.\n" + traceback.format_exc())
        self.cache.close(failed=True)

    def _close_writer(self) -> None:
        """Close the bag (summary, metadata.yaml); a failure to do so is recorded like any storage failure."""
        try:
            self.writer.close()
        except Exception as exc:  # noqa: BLE001 - recorded and logged; closing must not raise into finish()
            self._fail(exc)

    # --- end --------------------------------------------------------------------------------------------
    def finish(self, timeout: float | None = None, on_late_close: Callable[[], None] | None = None) -> None:
        """Flush the cache, close the bag (summary, metadata.yaml) and log the counts. Idempotent.

        Waits at most ``timeout`` seconds (None: as long as it takes) for the writer thread. One still busy
        then is slow or stuck on its storage: it is abandoned with the bag unfinalized, what was still queued is
        given up (``storage_failed``), and nothing that would wait on that storage (closing the bag, its counts)
        is attempted here. The messages the writer holds count as given up too until it gets to its end, if it
        ever does: it then closes the bag itself (:meth:`_end_of_writing`) and calls ``on_late_close``, after
        which :meth:`stats` are what the bag holds.
        """
        with self._finish_lock:
            if self._finished:
                return
            self._finished = True
        if self._snapshot_mode:
            self.cache.drain()  # a ring that was never snapshotted is simply discarded (a ring frees on take)
        self.cache.close()
        self._thread.join(timeout)
        self._discard(self.cache.drain(), STORAGE_FAILED)  # left behind by a failed or stuck writer
        with self._abandon_lock:
            self._abandoned = not self._writer_done and self._thread.is_alive()
            self._on_late_close = on_late_close
        self._encoder_final = self._encoder_deltas()
        if self._abandoned:
            self._fail(f"the writer did not finish within {timeout:.1f} s (a hung disk?): the bag was not "
                       "finalized; it can be repaired (ipc-component bag recover)")
        else:
            self._write_frame_accounts()
            self._close_writer()
        self._logger.info(self.summary())

    def _encoder_deltas(self) -> dict[str, dict[str, int]]:
        """Per encoder-published topic: what its encoder did with the raw frames since the bag took the topic."""
        if self._encoder_final is not None:
            return self._encoder_final
        with self._stats_lock:
            encoders = dict(self._encoders)
        deltas = {}
        for topic, (stream, base) in encoders.items():
            now = stream.stats()
            deltas[topic] = {name: now[name] - base[name] for name in _ENCODER_COUNTS}
        return deltas

    def _write_frame_accounts(self) -> None:
        """Each encoder-published topic's account of its raw frames, into metadata.yaml's custom_data."""
        stats = self.stats()
        pairs = {}
        for topic in self._encoder_final or {}:
            counts = stats["topics"][topic]
            pairs[frame_accounts.key(topic)] = frame_accounts.encode({
                "received": counts["received"], "written": counts["written"], **stats["drop_reasons"].get(topic, {}),
                RATE_LIMITED: counts[RATE_LIMITED]})
        if pairs:
            self.writer.update_custom_data(pairs)

    def _counts(self) -> _Counts:
        """Per topic: written, received, queue drops and the reasons of every drop; never waits on the storage."""
        idle = self._closed_late or not self._thread.is_alive()  # only then is the writer's lock free for sure
        handed = dict(self.handed)
        repeated = self.writer.repeated_counts
        written = {t: n - repeated.get(t, 0) for t, n in self.writer.written_message_counts.items()} if idle \
            else handed
        received, cache_full, refused = self.cache.counts()
        queue = Counter(self._queue_drops() if self._queue_drops else {})
        with self._stats_lock:
            reasons = defaultdict(Counter, {t: Counter(c) for t, c in self._writer_drops.items()})
            missed = Counter(self._missed)
            error = self.error
        with self._abandon_lock:
            given_up = self._abandoned and not self._writer_done
        # Only a failure loses accepted messages (the writer thread has stopped then, so the counts are still).
        lost_in_storage = {t: n - written.get(t, 0) for t, n in handed.items()} if error and idle else {}
        if given_up:  # what the abandoned writer holds (the queue was given up already): lost, unless it ends
            lost_in_storage = {t: n - cache_full[t] - refused[t] - handed.get(t, 0) - sum(reasons[t].values())
                               for t, n in received.items()}
        rate_limited = self._rate_limiter.left_out() if self._rate_limiter is not None else Counter()
        received += missed + rate_limited
        for topic, delta in self._encoder_deltas().items():  # the frames its encoder lost (module docstring)
            for count, reason in ENCODER_LOSSES.items():
                if delta[count] > 0:
                    reasons[topic][reason] += delta[count]
                    received[topic] += delta[count]
        for reason, counts in ((CACHE_FULL, cache_full), (STORAGE_FAILED, refused), (QUEUE_FULL, queue),
                               (STORAGE_FAILED, lost_in_storage), (RECORDING_STOPPED, missed)):
            for topic, count in counts.items():
                if count > 0:
                    reasons[topic][reason] += count
        topics = sorted(set(written) | self._topics | set(received) | set(queue))
        return _Counts(idle, written, received, queue, reasons, topics, rate_limited, repeated)

    def drop_reasons(self) -> dict[str, dict[str, int]]:
        """Per topic, per reason: messages dropped so far (what events/messages_lost reports the change of)."""
        counts = self._counts()
        return {t: dict(counts.reasons[t]) for t in counts.topics if counts.reasons[t]}

    def stats(self) -> dict[str, Any]:
        """Live counts per topic, with the reasons of every drop; never waits on the storage."""
        counts = self._counts()
        reasons, queue = counts.reasons, counts.queue
        with self._stats_lock:
            serialize_errors = dict(self.serialize_errors)
            error = self.error
        return {
            "bag": str(self.writer.path),
            "current_file": str(self.writer.current_file or ""),
            "bytes_written": self.writer.bytes_written if counts.idle else self._bytes_written,
            **self._backlog(),
            "free_bytes": self.disk.free,
            "seconds_until_min_free": self.disk.seconds_left,
            "deleted_files": list(self.writer.deleted_files),
            "error": error,
            "serialize_errors": serialize_errors,
            "write_latency_ms": _percentiles(list(self._latencies)),
            "topics": {t: {"received": counts.received[t], "written": counts.written.get(t, 0),
                           "dropped": sum(reasons[t].values()), "queue_dropped": queue[t],
                           RATE_LIMITED: counts.rate_limited[t], "repeated": counts.repeated.get(t, 0)}
                       for t in counts.topics},
            "drop_reasons": {t: dict(reasons[t]) for t in counts.topics if reasons[t]},
            "dropped_by_design": {t: {RATE_LIMITED: n} for t, n in sorted(counts.rate_limited.items()) if n},
        }

    def _backlog(self) -> dict[str, Any]:
        """What the writer has not written yet: bytes, how far behind (s) the oldest queued message is, and how
        much of the stall reserve that uses; the peak over the recording."""
        held, oldest_ns = self.cache.backlog()
        return {"cache_bytes": held, "backlog_bytes": held,
                "backlog_s": 0.0 if oldest_ns is None else max(0.0, (time.time_ns() - oldest_ns) / 1e9),
                "max_cache_size": self.cache.max_bytes, "stall_reserve": self.cache.reserve,
                "reserve_in_use_bytes": max(0, held - self.cache.max_bytes),
                "peak_backlog_bytes": self.cache.peak_bytes, "memory_returns": self.memory_returns,
                "memory_returned_bytes": self.memory_returned_bytes,
                "memory_return_pending": self.cache.reserve_entries != self._reserve_entries_returned}

    def summary(self) -> str:
        stats = self.stats()
        lines = [f"Bag {stats['bag']} closed: {sum(t['written'] for t in stats['topics'].values())} messages, "
                 f"{stats['bytes_written']} bytes" + (f", error: {stats['error']}" if stats["error"] else "")]
        for topic, counts in stats["topics"].items():
            lines.append(f"  {topic}: received {counts['received']}, written {counts['written']}, "
                         f"dropped {counts['dropped']}"
                         + (f", rate limited {counts[RATE_LIMITED]}" if counts[RATE_LIMITED] else ""))
        if stats["peak_backlog_bytes"] > stats["max_cache_size"]:
            lines.append(f"  the writer fell behind: backlog peaked at {stats['peak_backlog_bytes'] / 1e6:.0f} MB, "
                         f"{(stats['peak_backlog_bytes'] - stats['max_cache_size']) / 1e6:.0f} MB of the "
                         f"{stats['stall_reserve'] / 1e6:.0f} MB stall reserve")
        if stats["drop_reasons"]:
            lines.append("  dropped by reason: " + "; ".join(
                f"{topic} " + ", ".join(f"{reason} {n}" for reason, n in reasons.items())
                for topic, reasons in stats["drop_reasons"].items()))
        return "\n".join(lines)


@dataclass(frozen=True)
class _Counts:
    """One consistent reading of a session's per-topic counts (see RecordingSession._counts)."""

    idle: bool
    written: dict[str, int]
    received: Counter[str]
    queue: Counter[str]
    reasons: defaultdict[str, Counter[str]]
    topics: list[str]
    #: per topic: messages left out by record.max_rates (received, not lost)
    rate_limited: Counter[str]
    #: per topic: latched messages written again at splits and snapshots (record.repeat_transient_local)
    repeated: dict[str, int]


def _log_time(message: CachedMessage) -> int:
    return message.log_time_ns
