"""The player's clock of bag time (rosbag2's TimeControllerClock): rate, pause, jump, and a sleeper that a
control wakes up. Plain threads, no ROS."""
from __future__ import annotations

import threading
import time

from components.player.playback_clock import PlaybackClock

MS = 1_000_000
T0 = 1_700_000_000_000_000_000


def test_bag_time_runs_at_the_rate() -> None:
    clock = PlaybackClock(T0, rate=2.0)
    time.sleep(0.1)
    assert 150 * MS < clock.now() - T0 < 300 * MS
    assert not clock.set_rate(0.0) and not clock.set_rate(-1.0) and clock.rate == 2.0


def test_pause_holds_bag_time_and_resume_continues_without_a_step() -> None:
    clock = PlaybackClock(T0)
    time.sleep(0.05)
    clock.pause()
    held = clock.now()
    time.sleep(0.1)
    assert clock.now() == held and clock.steady_for(held + MS) is None
    clock.resume()
    assert 0 <= clock.now() - held < 20 * MS


def test_sleep_until_is_punctual_and_a_control_wakes_the_sleeper() -> None:
    clock = PlaybackClock(T0)
    due = T0 + 50 * MS
    assert clock.sleep_until(due)
    assert clock.now() >= due
    results: list[bool] = []
    sleeper = threading.Thread(target=lambda: results.append(clock.sleep_until(clock.now() + 10_000 * MS)))
    sleeper.start()
    time.sleep(0.05)
    clock.jump(T0)  # a seek: the schedule moved
    sleeper.join(1.0)
    assert results == [False]


def test_a_paused_sleeper_waits_for_resume() -> None:
    clock = PlaybackClock(T0, paused=True)
    started = time.monotonic()
    assert not clock.sleep_until(T0 + MS, timeout=0.1)  # still paused after the timeout
    assert time.monotonic() - started >= 0.09
    threading.Timer(0.05, clock.resume).start()
    assert not clock.sleep_until(T0 + MS)  # resume is a change: the caller looks again
    assert clock.sleep_until(T0 + MS)
