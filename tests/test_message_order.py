"""The read-ahead's publish-time order (``play.message_order`` SENT_TIMESTAMP): the sorting window itself, on
messages read back from a real bag. The player publishing in that order is tested in test_player.py."""
from __future__ import annotations

from pathlib import Path

from std_msgs.msg import String

from baglib.format.cdr_fast import serialize
from baglib.format.metadata import TopicInfo
from baglib.read.timeline import Timeline
from baglib.write.writer import BagWriter
from components.player.read_ahead import Queued, publish_order

T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def items(tmp_path: Path, times: list[tuple[int, int]]) -> list[Queued]:
    """A bag of one /chatter message per (receive ms, publish ms), read back as the loader queues them."""
    with BagWriter(tmp_path / "bag") as writer:
        writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String"))
        for n, (received, published) in enumerate(times):
            writer.write("/chatter", bytes(serialize(String(data=str(n)))), T0 + received * MS,
                         T0 + published * MS if published >= 0 else 0)
    timeline = Timeline([tmp_path / "bag"])
    return [Queued(message, message.log_time_ns) for message in timeline.messages(["/chatter"], 0, None)]


def order(result: list[Queued]) -> list[tuple[str, int]]:
    """(data, due ms from T0) of each item."""
    return [(bytes(item.message.data)[8:-1].decode(), (item.time_ns - T0) // MS) for item in result]


def test_sorted_by_publish_time_within_the_window(tmp_path: Path) -> None:
    queued = items(tmp_path, [(10, 9), (20, 5), (30, 25), (40, 22)])
    assert order(list(publish_order(queued, T0, 1000, 1 << 30))) == [("1", 5), ("0", 9), ("3", 22), ("2", 25)]


def test_equal_publish_times_keep_bag_order_and_nothing_is_due_before_the_start(tmp_path: Path) -> None:
    queued = items(tmp_path, [(10, 4), (11, 4), (12, 4), (30, 20)])
    assert order(list(publish_order(queued, T0 + 10 * MS, 1000, 1 << 30))) == [
        ("0", 10), ("1", 10), ("2", 10), ("3", 20)]


def test_a_message_beyond_the_window_goes_out_at_once_and_the_due_times_never_go_back(tmp_path: Path) -> None:
    """A window of one message (the newest read is sorted against it): message 3, published first of all, is read
    when 0 and 1 have left; it is due with the one before it, not back in time, so the rest keep their schedule."""
    queued = items(tmp_path, [(10, 8), (20, 18), (30, 28), (40, 1), (50, 48)])
    assert order(list(publish_order(queued, T0, 1, 1 << 30))) == [
        ("0", 8), ("1", 18), ("3", 18), ("2", 28), ("4", 48)]


def test_the_byte_bound_shrinks_the_window_to_one_message(tmp_path: Path) -> None:
    times = [(10, 9), (20, 15), (30, 5)]
    assert order(list(publish_order(items(tmp_path / "a", times), T0, 1000, 1 << 30))) == [
        ("2", 5), ("0", 9), ("1", 15)]
    assert order(list(publish_order(items(tmp_path / "b", times), T0, 1000, 1))) == [
        ("0", 9), ("2", 9), ("1", 15)]


def test_a_message_without_publish_time_counts_at_its_receive_time(tmp_path: Path) -> None:
    queued = items(tmp_path, [(10, -1), (20, 5)])  # MCAP publish_time 0: not set by its writer
    assert order(list(publish_order(queued, T0, 1000, 1 << 30))) == [("1", 5), ("0", 10)]
