"""The player's clock of bag time (rosbag2's TimeControllerClock): rate, pause, jump, and a sleeper that a
control wakes up. Plain threads, no ROS.

The arithmetic of bag time is checked against a fake steady clock (exact values, nothing timed); the sleeper
tests run on the real clock and check order: what a call returns and what the clock says afterwards, never how
long anything took (the player's punctuality is the replay benchmark's measure).
"""
from __future__ import annotations

import threading
import time
import types
from typing import Any, Callable

import pytest

from components.player import playback_clock
from components.player.playback_clock import PlaybackClock

MS = 1_000_000
T0 = 1_700_000_000_000_000_000
#: How long a thread may take to reach its wait before the test fails: a guard against hanging only.
PATIENCE_S = 20.0


class FakeSteadyClock:
    """The clock module's ``time.monotonic_ns``, advanced by hand."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.ns = 5_000_000_000
        monkeypatch.setattr(playback_clock, "time", types.SimpleNamespace(monotonic_ns=lambda: self.ns))

    def advance(self, ns: int) -> None:
        self.ns += ns


def wait_for(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + PATIENCE_S
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.001)


def waiting(clock: PlaybackClock) -> bool:
    """Whether a thread waits on the clock's condition (it released the lock inside ``wait``)."""
    return bool(clock._changed._waiters)  # type: ignore[attr-defined]


def test_bag_time_runs_at_the_rate(monkeypatch: pytest.MonkeyPatch) -> None:
    steady = FakeSteadyClock(monkeypatch)
    clock = PlaybackClock(T0, rate=2.0)
    assert clock.now() == T0
    steady.advance(100 * MS)
    assert clock.now() == T0 + 200 * MS
    assert clock.steady_for(T0 + 300 * MS) == steady.ns + 50 * MS
    assert not clock.set_rate(0.0) and not clock.set_rate(-1.0) and clock.rate == 2.0
    assert clock.now() == T0 + 200 * MS
    assert clock.set_rate(0.5)  # from here on half speed, no step
    steady.advance(100 * MS)
    assert clock.now() == T0 + 250 * MS


def test_pause_holds_bag_time_and_resume_continues_without_a_step(monkeypatch: pytest.MonkeyPatch) -> None:
    steady = FakeSteadyClock(monkeypatch)
    clock = PlaybackClock(T0)
    steady.advance(50 * MS)
    clock.pause()
    held = clock.now()
    assert held == T0 + 50 * MS
    steady.advance(100 * MS)
    assert clock.now() == held and clock.steady_for(held + MS) is None
    clock.resume()
    assert clock.now() == held  # no step: bag time goes on from where it was held
    steady.advance(5 * MS)
    assert clock.now() == held + 5 * MS
    clock.jump(T0)
    assert clock.now() == T0


def test_sleep_until_is_punctual_and_a_control_wakes_the_sleeper() -> None:
    clock = PlaybackClock(T0)
    due = T0 + 50 * MS
    assert clock.sleep_until(due)
    assert clock.now() >= due
    results: list[bool] = []
    sleeper = threading.Thread(target=lambda: results.append(clock.sleep_until(clock.now() + 10_000 * MS)))
    sleeper.start()
    wait_for(lambda: waiting(clock), "the sleeper never waited")
    clock.jump(T0)  # a seek: the schedule moved
    sleeper.join(PATIENCE_S)
    assert results == [False]


def test_a_paused_sleeper_waits_for_resume(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = PlaybackClock(T0, paused=True)
    waits: list[tuple[Any, bool]] = []  # (timeout, whether it was woken before the timeout)
    real_wait = clock._changed.wait

    def recorded_wait(timeout: Any = None) -> bool:
        woken = real_wait(timeout)
        waits.append((timeout, woken))
        return woken

    monkeypatch.setattr(clock._changed, "wait", recorded_wait)
    assert not clock.sleep_until(T0 + MS, timeout=0.1)  # still paused after the timeout
    assert waits == [(0.1, False)], "not one wait of the given timeout, to its end"
    results: list[bool] = []
    sleeper = threading.Thread(target=lambda: results.append(clock.sleep_until(T0 + MS, timeout=PATIENCE_S)))
    sleeper.start()
    wait_for(lambda: waiting(clock), "the sleeper never waited")
    clock.resume()
    sleeper.join(PATIENCE_S)
    assert results == [False]  # resume is a change: the caller looks again ...
    assert waits[1:] == [(PATIENCE_S, True)]  # ... woken by it, not by its timeout
    assert clock.sleep_until(T0 + MS)
