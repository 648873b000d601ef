"""The playback engine: one thread that publishes each message when the bag's clock reaches it.

The shape is rosbag2_transport's PlayerImpl: ``play()`` starts a run (delay, then from the start offset to the
end or the "until" time, again and again with ``loop``); ``pause``/``resume``/``set_rate`` steer the clock;
``play_next``, ``burst`` and ``seek`` take over the next message from the main loop under one lock, so a
message is never published twice or skipped; ``stop`` ends the run. Each message is due at its ``time_ns``
(its receive time, or its publish time with ``play.message_order`` SENT_TIMESTAMP: read_ahead.py orders the
queue); messages with equal times keep the bag's order (the reader's guarantee; the queue never reorders them).

Preparing: turning a recorded message into the object in-process subscribers get (deserializing a 6 MB
frame: 0.3 to several ms, holding the GIL) is done by this same thread, in the time it would otherwise sleep:
before waiting for a message, it prepares that message and then as many of the queued ones after it as fit
before it is due (costs measured per topic). Done on another thread, it would hold the GIL exactly when the
playback thread wakes up for a due message. A decoded topic's message is the exception: its stream's decoding
thread made its objects (decoded_topics.py); this thread takes them before it sleeps until the message is due,
waiting for them only if that decoder is late. Decoders start cold (FFmpeg's threads, new buffers: the first
frames of a stream take ten times as long), so a run's pass with decoded topics starts its clock only once they are
ahead: the pictures of its first :data:`HEAD_START_NS` of bag time decoded (waiting at most
:data:`HEAD_START_TIMEOUT_S`); without that, every stream's first frames went out late, each moving the schedule
back.

A run that ends (its end, the "until" time, ``stop``) halts the read-ahead: the queue is dropped and the decoding
threads end.

Falling behind: a message that goes out more than :data:`BEHIND_NS` after its scheduled time moves the whole
schedule back by that lateness instead of publishing the following messages in a catch-up burst; the shifts
are counted and logged, so a player that cannot keep up slows down smoothly and says so: the first time at
once, then at most every :data:`BEHIND_WARN_EVERY_NS` with what happened since (how often, and the worst lag: as
rclcpp's throttled logging, one line stands for many), and once more at the end of the run if anything is left
unsaid (a busy machine falls behind every second; a line per second would bury everything else).
"""
from __future__ import annotations

import threading
import time
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from baglib.read.reader import BagMessage
from components.player.playback_clock import PlaybackClock
from components.player.read_ahead import Queued, ReadAhead

#: Lateness (steady time) beyond which the schedule is moved instead of caught up.
BEHIND_NS = 10_000_000
#: How many queued messages the playback thread looks at to prepare while it waits for the next one.
PREPARE_AHEAD = 64
#: Time kept free before a message is due when preparing others ahead of it.
PREPARE_MARGIN_NS = 500_000
#: Bag time a run's pass of decoded topics has decoded before its clock starts, and how long it waits for that.
HEAD_START_NS = 250_000_000
HEAD_START_TIMEOUT_S = 1.0
#: Publish-time errors kept for the percentiles (the newest ones).
TIMING_SAMPLES = 100_000
_WARN_EVERY_NS = 1_000_000_000
#: How often falling behind is reported at most, after its first report.
BEHIND_WARN_EVERY_NS = 10_000_000_000


@dataclass
class RunLimits:
    """One run's range: rosbag2's start_offset, and play_until_timestamp (-1: none, 0: publish nothing)."""

    start_ns: int
    until_ns: int = -1

    def stops_at(self, time_ns: int) -> bool:
        return self.until_ns == 0 or (self.until_ns > -1 and time_ns > self.until_ns)


class PublishTiming:
    """Publish time error (actual − scheduled, steady ns) of the messages played by the main loop."""

    def __init__(self) -> None:
        self._errors = array("q")
        self._lock = threading.Lock()
        self.count = 0

    def add(self, error_ns: int) -> None:
        with self._lock:
            if len(self._errors) >= TIMING_SAMPLES:
                del self._errors[: TIMING_SAMPLES // 10]
            self._errors.append(error_ns)
            self.count += 1

    def percentiles(self, *quantiles: float) -> list[float]:
        """Errors in milliseconds at ``quantiles`` (0..1) over the kept samples; NaN without samples."""
        with self._lock:
            ordered = sorted(self._errors)
        if not ordered:
            return [float("nan")] * len(quantiles)
        return [ordered[min(len(ordered) - 1, int(q * len(ordered)))] / 1e6 for q in quantiles]


class Playback:
    """Runs the playback thread of a player node; every method is thread-safe."""

    def __init__(self, clock: PlaybackClock, read_ahead: ReadAhead, bag_start_ns: int,
                 prepare: Callable[[BagMessage], Any], publish: Callable[[Queued], bool], log: Any,
                 loop: bool = False, delay_ns: int = 0,
                 on_run_end: Callable[[], None] = lambda: None,
                 on_bag_end: Callable[[], None] = lambda: None) -> None:
        self.clock = clock
        self._read_ahead = read_ahead
        self._make = prepare
        self._costs: dict[str, int] = {}   # topic -> recent preparing time (moving average), ns
        self._publish = publish
        self._on_run_end = on_run_end
        self._on_bag_end = on_bag_end
        self._log = log
        self._loop = loop
        self._delay_ns = max(delay_ns, 0)
        if delay_ns < 0:
            log.warning(f"Invalid delay value: {delay_ns}. Delay is disabled.")
        self._take_over = threading.Lock()  # rosbag2's skip_message_in_main_play_loop_mutex_
        self._skip = False                  # a take-over happened: the main loop must peek again
        self._stop = threading.Event()
        self._playing = threading.Lock()    # held by a run from play() to its end
        self._thread: threading.Thread | None = None
        self.limits = RunLimits(bag_start_ns)
        self.timing = PublishTiming()
        self.position_ns = bag_start_ns     # bag time of the last message published
        self.behind_count = 0
        self.behind_ns = 0                  # total schedule shift, steady ns
        self._last_warning = 0
        self._behind_reported: tuple[int, int] | None = None  # (steady ns, behind_count) of the last report
        self._worst_late_ns = 0             # the worst lateness since the last report

    # --- runs ---------------------------------------------------------------------------------------------
    @property
    def in_playback(self) -> bool:
        return self._playing.locked()

    def play(self, limits: RunLimits) -> bool:
        """Start a run in a new thread; False (and a warning) while a run is going on, as rosbag2."""
        if not self._playing.acquire(blocking=False):
            self._log.warning("Trying to play() while in playback, dismissing request.")
            return False
        if self._thread is not None:
            self._thread.join()
        self.limits = limits
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="player-playback", daemon=True)
        self._thread.start()
        return True

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def stop(self, timeout: float) -> bool:
        """End the run (a paused one too, staying paused); True if its thread ended within ``timeout``."""
        self._stop.set()
        with self._take_over:
            self._skip = True
        self.clock.wake()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)
            return not thread.is_alive()
        return True

    def wait_finished(self, timeout: float) -> bool:
        thread = self._thread
        if thread is not None:
            thread.join(timeout)
        return not self.in_playback

    def _run(self) -> None:
        try:
            while True:
                if self._delay_ns and self._stop.wait(self._delay_ns / 1e9):
                    break
                start = self.limits.start_ns
                with self._take_over:
                    self._skip = False
                    self._read_ahead.restart(start)
                    self.clock.jump(start)
                if self._play_queue():
                    self._on_bag_end()
                if self._stop.is_set() or not self._loop:
                    break
        except Exception as exc:  # noqa: BLE001 - rosbag2 logs "Failed to play" and ends the run
            self._log.error(f"Failed to play: {exc}")
        finally:
            self._report_behind(time.monotonic_ns(), final=True)
            self._read_ahead.halt()  # nothing queued stays in memory, no decoder works for a run that ended
            try:
                self._on_run_end()
            finally:
                self._playing.release()

    def _play_queue(self) -> bool:
        """Play the current pass; True if it reached the end of the bag (not a stop or the "until" time)."""
        self._head_start()
        while not self._stop.is_set():
            item = self._next()
            if item is None:
                if not self._read_ahead.at_end:
                    continue
                if self.clock.paused:  # rosbag2 stays in the run while paused at the end (seek may follow)
                    self.clock.sleep_until(self.clock.now() + 1)
                    continue
                return True
            due = item.time_ns
            if self.limits.stops_at(due):
                return False
            self._prepare(item)
            self._prepare_ahead(self.clock.steady_for(due))
            if not self.clock.sleep_until(due):
                continue  # the schedule moved (pause, rate, seek, take-over, stop): look again
            with self._take_over:
                if self._skip:
                    self._skip = False
                    continue
                scheduled = self.clock.steady_for(due)
                if scheduled is None:  # paused between the wake-up and here
                    continue
                late = time.monotonic_ns() - scheduled  # when publishing starts: the message's publish time
                self.timing.add(late)
                self._publish_now(item)
                if late > BEHIND_NS:
                    self._fall_behind(due, late)
        return False

    def _head_start(self) -> None:
        """Start the pass's clock again once its decoders are ahead (a pass without decoded topics starts at
        once): the pictures of its first HEAD_START_NS decoded, waiting at most HEAD_START_TIMEOUT_S."""
        if self._read_ahead.wait_decoded(HEAD_START_NS, HEAD_START_TIMEOUT_S):
            with self._take_over:
                if not self._skip:  # a seek or play_next meanwhile has set the schedule itself
                    self.clock.jump(self.limits.start_ns)

    def _prepare(self, item: Queued) -> None:
        if item.ready:
            return
        if item.decoding is not None:
            item.take_decoded()  # its stream's thread made the objects; waits only if that decoder is late
            return
        started = time.monotonic_ns()
        item.prepared = self._make(item.message)
        item.ready = True
        topic = item.message.connection.topic
        cost = time.monotonic_ns() - started
        self._costs[topic] = (3 * self._costs.get(topic, cost) + cost) // 4  # a moving average

    def _prepare_ahead(self, due_ns: int | None) -> None:
        """Prepare queued messages after the next one while they fit before it is due (None: paused)."""
        for item in self._read_ahead.head(PREPARE_AHEAD)[1:]:
            if item.ready or item.decoding is not None:
                continue
            if due_ns is not None and (time.monotonic_ns() + self._costs.get(item.message.connection.topic, 0)
                                       + PREPARE_MARGIN_NS > due_ns):
                continue  # does not fit before the next one is due; a cheaper one further on may
            self._prepare(item)

    def _next(self) -> Queued | None:
        item = self._read_ahead.peek(0.1)
        if item is None and not self._read_ahead.at_end and not self._stop.is_set():
            now = time.monotonic_ns()
            if now - self._last_warning > _WARN_EVERY_NS:
                self._last_warning = now
                self._log.warning("Message queue starved. Messages will be delayed. Consider increasing the "
                                  "play.read_ahead_queue_size / play.read_ahead_max_bytes parameters.")
        return item

    def _publish_now(self, item: Queued) -> bool:
        self._prepare(item)
        published = self._publish(item)
        self.position_ns = item.time_ns
        self._read_ahead.pop()
        return published

    def _fall_behind(self, due: int, late_ns: int) -> None:
        self.clock.jump(due)  # the message just published is "now": the rest keep their spacing
        self.behind_count += 1
        self.behind_ns += late_ns
        self._worst_late_ns = max(self._worst_late_ns, late_ns)
        self._report_behind(time.monotonic_ns(), final=False)

    def _report_behind(self, now: int, final: bool) -> None:
        """Log falling behind: the first time, then at most every BEHIND_WARN_EVERY_NS, and at the run's end."""
        last = self._behind_reported
        unsaid = self.behind_count - (last[1] if last else 0)
        if not unsaid or (last is not None and not final and now - last[0] < BEHIND_WARN_EVERY_NS):
            return
        self._behind_reported = (now, self.behind_count)
        lag, self._worst_late_ns = self._worst_late_ns / 1e6, 0
        if last is None:
            what = f"Playback is {lag:.1f} ms behind schedule"
        else:
            what = (f"Playback fell behind schedule {_times(unsaid)} in the last {(now - last[0]) / 1e9:.0f} s, "
                    f"by up to {lag:.1f} ms,")
        self._log.warning(
            f"{what} at rate {self.clock.rate:g} (reading or publishing cannot keep up); the schedule moves back "
            f"instead of catching up ({_times(self.behind_count)} so far, {self.behind_ns / 1e9:.3f} s in all)")

    # --- take-overs (rosbag2: play_next, burst, seek) -----------------------------------------------------
    def play_next(self) -> bool:
        """Publish the next message now; only while paused (False otherwise, or at the end of the bag)."""
        if not self.clock.paused:
            self._log.warning("Called play next, but not in paused state.")
            return False
        with self._take_over:
            if not self.clock.paused or not self.in_playback:
                return False
            self._skip = True
            while not self._stop.is_set():
                item = self._read_ahead.peek(1.0)
                if item is None:
                    if self._read_ahead.at_end:
                        return False
                    continue
                if self.limits.stops_at(item.time_ns):
                    return False
                published = self._publish_now(item)
                self.clock.jump(item.time_ns)
                if published:
                    return True
            return False

    def burst(self, count: int) -> int:
        """Publish up to ``count`` messages at once while paused (0: the rest of the bag)."""
        if not self.clock.paused:
            self._log.warning("Burst can only be used when in the paused state.")
            return 0
        played = 0
        while (count == 0 or played < count) and self.play_next():
            played += 1
        self._log.info(f"Burst {played} messages.")
        return played

    def seek(self, time_ns: int) -> None:
        """Continue from bag time ``time_ns`` (clamped to the run's start), paused or not."""
        with self._take_over:
            self._skip = True
            time_ns = max(time_ns, self.limits.start_ns)
            self._read_ahead.restart(time_ns)
            self.clock.jump(time_ns)
            self.position_ns = time_ns


def _times(count: int) -> str:
    return f"{count} time{'' if count == 1 else 's'}"
