"""Bag time against the steady clock: rosbag2's ``TimeControllerClock`` (rate, pause, jump), for one thread
that sleeps until a message is due while others steer.

The clock is one anchor, a (bag time, steady time) pair, plus a rate: bag time advances ``rate`` ns per
steady ns from the anchor. Every control (set_rate, pause, resume, jump) re-anchors at the current bag time
and wakes the sleeper, which then sleeps again against the new schedule: no step in bag time, no catch-up.
"""
from __future__ import annotations

import threading
import time

#: The last stretch before a message is due is spent polling, not in a condition wait: a timed wait can
#: overshoot by the scheduler's slice, and the timing target is a p99 error under 2 ms. The poll keeps the
#: GIL: releasing it (``sleep(0)``) would let a busy thread keep it for a whole switch interval.
SPIN_NS = 300_000


class PlaybackClock:
    """rosbag2_cpp::TimeControllerClock in Python: ``now()`` in bag nanoseconds, ``sleep_until(t)``."""

    def __init__(self, start_ns: int, rate: float = 1.0, paused: bool = False) -> None:
        if rate <= 0:
            raise ValueError(f"rate must be > 0, got {rate}")
        self._changed = threading.Condition()
        self._rate = rate
        self._paused = paused
        self._anchor_bag = start_ns
        self._anchor_steady = time.monotonic_ns()
        self._generation = 0  # counts controls, so a sleeper knows the schedule moved

    # --- reading ------------------------------------------------------------------------------------------
    @property
    def rate(self) -> float:
        return self._rate

    @property
    def paused(self) -> bool:
        return self._paused

    def now(self) -> int:
        """The current bag time."""
        with self._changed:
            return self._now(time.monotonic_ns())

    def _now(self, steady: int) -> int:
        if self._paused:
            return self._anchor_bag
        return self._anchor_bag + int((steady - self._anchor_steady) * self._rate)

    def steady_for(self, bag_ns: int) -> int | None:
        """The steady time at which bag time reaches ``bag_ns``; None while paused."""
        with self._changed:
            if self._paused:
                return None
            return self._anchor_steady + int((bag_ns - self._anchor_bag) / self._rate)

    # --- steering -----------------------------------------------------------------------------------------
    def set_rate(self, rate: float) -> bool:
        """False (and nothing changes) unless ``rate`` > 0, as rosbag2's set_rate."""
        if not rate > 0:
            return False
        with self._changed:
            self._reanchor(self._now(time.monotonic_ns()))
            self._rate = rate
        return True

    def pause(self) -> None:
        with self._changed:
            if not self._paused:
                self._reanchor(self._now(time.monotonic_ns()))
                self._paused = True

    def resume(self) -> None:
        with self._changed:
            if self._paused:
                self._paused = False
                self._reanchor(self._anchor_bag)

    def jump(self, bag_ns: int) -> None:
        """Bag time is ``bag_ns`` from now on (seek, a new loop, a player falling behind)."""
        with self._changed:
            self._reanchor(bag_ns)

    def wake(self) -> None:
        """Make a sleeper return early (stop, seek): it returns False as for any change."""
        with self._changed:
            self._generation += 1
            self._changed.notify_all()

    def _reanchor(self, bag_ns: int) -> None:
        self._anchor_bag = bag_ns
        self._anchor_steady = time.monotonic_ns()
        self._generation += 1
        self._changed.notify_all()

    # --- waiting ------------------------------------------------------------------------------------------
    def sleep_until(self, bag_ns: int, timeout: float = 1.0) -> bool:
        """Sleep until bag time reaches ``bag_ns``: True when it has, False if a control moved the schedule
        (or ``timeout`` seconds passed while paused) first; the caller then decides and calls again."""
        with self._changed:
            generation = self._generation
            while True:
                if self._generation != generation:
                    return False
                if self._paused:
                    self._changed.wait(timeout)
                    if self._paused and self._generation == generation:
                        return False
                    continue
                deadline = self._anchor_steady + int((bag_ns - self._anchor_bag) / self._rate)
                remaining = deadline - time.monotonic_ns()
                if remaining <= 0:
                    return True
                if remaining > SPIN_NS:
                    self._changed.wait((remaining - SPIN_NS) / 1e9)
                    continue
                break
        while time.monotonic_ns() < deadline:  # the last few hundred µs: the clock's lock released, not the GIL
            if self._generation != generation:
                return False
        return True
