"""What the playback engine says when it cannot keep up: enough to know, not a line every second.

A real bag read through the player's own read-ahead and clock; the "publisher" is a function that takes 12 ms per
message for a bag recorded at 1 kHz (two messages in the middle take 80 ms each: whichever of them is on time,
the message after it is late by about that), so every message is late and the
schedule moves back each time, as on a machine too busy to publish at the recorded rate. No ROS.
"""
from __future__ import annotations

import re
import threading
import time
from pathlib import Path
from typing import Any

from std_msgs.msg import String

from baglib.format.cdr_fast import serialize
from baglib.format.metadata import TopicInfo
from baglib.read.timeline import Timeline
from baglib.write.writer import BagWriter
from components.player.playback import BEHIND_WARN_EVERY_NS, Playback, RunLimits
from components.player.playback_clock import PlaybackClock
from components.player.read_ahead import ReadAhead

T0 = 1_700_000_000_000_000_000
MESSAGES = 250
PUBLISH_S = 0.012  # 12 times the recorded period: every message is more than BEHIND_NS late
SLOWEST_S = 0.080  # the two publishes in the middle that take longer: the worst lag follows them
PATIENCE_S = 60.0  # a guard against hanging only


class Lines:
    """A logger that keeps what it is told, by level."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def __getattr__(self, level: str) -> Any:
        return lambda message: self.lines.append((level, message))


def test_falling_behind_is_reported_first_then_summed_up(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as writer:
        writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String"))
        for n in range(MESSAGES):
            writer.write("/chatter", bytes(serialize(String(data=str(n)))), T0 + n * 1_000_000, T0 + n * 1_000_000)
    timeline = Timeline([tmp_path / "bag"])
    read_ahead = ReadAhead(timeline, ["/chatter"], 1000, 1 << 30, lambda error: None)
    log = Lines()
    ended = threading.Event()

    published: list[Any] = []

    def publish(item: Any) -> bool:
        published.append(item)
        time.sleep(SLOWEST_S if len(published) in (MESSAGES // 2, MESSAGES // 2 + 1) else PUBLISH_S)
        return True

    playback = Playback(PlaybackClock(T0), read_ahead, T0, lambda message: message, publish, log,
                        on_run_end=ended.set)
    try:
        started = time.monotonic()
        assert playback.play(RunLimits(T0))
        assert ended.wait(PATIENCE_S), "the run never ended"
        elapsed_ns = (time.monotonic() - started) * 1e9
    finally:
        playback.stop(5.0)
        read_ahead.close()
        timeline.close()
    behind = [message for level, message in log.lines if "behind schedule" in message]
    assert playback.behind_count >= MESSAGES // 2
    # The first at once, one per BEHIND_WARN_EVERY_NS after it at most, and the end of the run: the run lasts
    # MESSAGES * PUBLISH_S (3 s or more), which was a line per second when it was reported every second.
    assert 2 <= len(behind) <= 2 + elapsed_ns // BEHIND_WARN_EVERY_NS, behind
    assert all(level == "warning" for level, message in log.lines if message in behind)
    assert behind[-1].endswith(f"{playback.behind_count} times so far, {playback.behind_ns / 1e9:.3f} s in all)")
    # a summary line says how often since the line before, and the worst lag among them (not the latest)
    summary = re.search(r"fell behind schedule (\d+) times in the last \d+ s, by up to ([\d.]+) ms,", behind[-1])
    assert summary and float(summary[2]) >= SLOWEST_S * 1e3 - 5, behind[-1]
