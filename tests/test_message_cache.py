"""The recorder's cache bound is honest: every message counts for what it serializes to, not for a ``data`` field.

Real message objects of the types a robot records besides images and clouds (scans, markers, paths, pose
arrays), sized against rclpy's own serialization.
"""
from __future__ import annotations

import threading
import time
import types
from typing import Any, Callable

import pytest
from geometry_msgs.msg import Pose, PoseArray, PoseStamped
from nav_msgs.msg import Path
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image, Imu, LaserScan
from visualization_msgs.msg import Marker, MarkerArray

from components.recorder import message_cache
from components.recorder.message_cache import CachedMessage, MessageCache, payload_size


def laser_scan() -> LaserScan:
    return LaserScan(ranges=[1.5] * 1440, intensities=[100.0] * 1440)


def marker_array() -> MarkerArray:
    return MarkerArray(markers=[Marker(id=i, text=f"marker {i}", points=[Pose().position] * 20) for i in range(30)])


def path() -> Path:
    return Path(poses=[PoseStamped() for _ in range(500)])


def pose_array() -> PoseArray:  # tf2_msgs (TFMessage) is not among the installed wheels; the same shape
    return PoseArray(poses=[Pose() for _ in range(400)])


@pytest.mark.parametrize("make", [laser_scan, marker_array, path, pose_array])
def test_cache_bound_counts_serialized_size(make: Callable[[], Any]) -> None:
    real = len(serialize_message(make()))
    assert payload_size(make()) == real
    cache = MessageCache(max_bytes=10 * real + real // 2)
    accepted = [cache.push(CachedMessage("/t", make(), payload_size(make()), i, i)) for i in range(20)]
    assert accepted == [True] * 10 + [False] * 10, f"{real} bytes each in a {cache.max_bytes} byte cache"
    assert cache.dropped["/t"] == 10 and cache.bytes == 10 * real


def test_images_are_never_undercounted() -> None:
    image = Image(encoding="rgb8", width=64, height=48, step=192, data=bytes(64 * 48 * 3))
    image.header.frame_id = "camera_optical_frame"
    real = len(serialize_message(image))
    assert real <= payload_size(image) <= real + 64


def test_broken_message_is_sized_without_raising() -> None:
    scan = LaserScan()
    scan.angle_min = "not a float"  # field checks are off by default in Jazzy: this only fails at serialization
    assert payload_size(scan) > 0


def _message(size: int = 100) -> CachedMessage:
    return CachedMessage("/t", b"x" * size, size, 0, 0)


#: How long a thread may take to reach its wait, or to return, before the test fails: a guard against
#: hanging only (every wait below ends by a push, a notify or a close, never by time).
PATIENCE_S = 20.0


class Gathering:
    """A cache whose steady clock stands still unless the test moves it (so a gather never ends by time
    unless the test says so), and a ``take_all`` in a thread of its own."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, max_bytes: int) -> None:
        self.now = 1000.0
        monkeypatch.setattr(message_cache, "time", types.SimpleNamespace(monotonic=lambda: self.now))
        self.cache = MessageCache(max_bytes=max_bytes)
        self.waits = 0
        real_wait = self.cache._condition.wait

        def counted_wait(timeout: float | None = None) -> bool:
            self.waits += 1  # under the cache's lock: the pusher sees it once the wait released it
            return real_wait(timeout)

        monkeypatch.setattr(self.cache._condition, "wait", counted_wait)
        self.batches: list[list[CachedMessage]] = []
        self.thread: threading.Thread | None = None

    def take_all(self, timeout: float, gather: float) -> None:
        self.thread = threading.Thread(target=lambda: self.batches.append(self.cache.take_all(timeout, gather)),
                                       daemon=True)
        self.thread.start()

    def wait_for_waits(self, count: int) -> None:
        """Until the taker has entered its ``count``-th wait (and released the lock in it)."""
        deadline = time.monotonic() + PATIENCE_S
        while True:
            with self.cache._mutex:
                if self.waits >= count:
                    return
            assert time.monotonic() < deadline, f"take_all never waited {count} times"
            time.sleep(0.001)

    def result(self) -> list[CachedMessage]:
        assert self.thread is not None
        self.thread.join(PATIENCE_S)
        assert not self.thread.is_alive(), "take_all did not return"
        return self.batches[-1]


def test_take_all_lets_a_batch_gather(monkeypatch: pytest.MonkeyPatch) -> None:
    """The writer is woken once for messages that arrive within ``gather`` of its previous take, not per message."""
    gathering = Gathering(monkeypatch, max_bytes=1 << 20)
    cache = gathering.cache
    assert cache.take_all(timeout=0.0) == []  # the previous take
    gathering.take_all(timeout=PATIENCE_S, gather=1.0)
    gathering.wait_for_waits(1)  # for something to arrive
    cache.push(_message())
    gathering.wait_for_waits(2)  # gathering
    for _ in range(4):
        cache.push(_message())
    assert gathering.thread is not None and gathering.thread.is_alive() and not gathering.batches
    with cache._condition:  # the gather time passes
        gathering.now += 1.5
        cache._condition.notify_all()
    assert len(gathering.result()) == 5


def test_take_all_stops_gathering_at_a_quarter_of_the_cache_or_a_close(monkeypatch: pytest.MonkeyPatch) -> None:
    """Gathering never risks a drop that taking at once would avoid, and never delays the final flush: with the
    clock standing still, only a quarter of the cache queued or a close can end a gather of 60 s."""
    gathering = Gathering(monkeypatch, max_bytes=4000)
    cache = gathering.cache
    cache.take_all(timeout=0.0)
    gathering.take_all(timeout=PATIENCE_S, gather=60.0)
    gathering.wait_for_waits(1)
    cache.push(_message(600))
    gathering.wait_for_waits(2)
    cache.push(_message(600))  # 1200 bytes: past a quarter of 4000
    batch = gathering.result()
    assert len(batch) == 2
    for message in batch:  # written: as the writer does, they stop counting against the bound
        cache.release(message.size)
    cache.push(_message())
    gathering.take_all(timeout=PATIENCE_S, gather=60.0)
    gathering.wait_for_waits(3)  # gathering the one message
    cache.close()
    assert len(gathering.result()) == 1 and cache.closed


@pytest.mark.parametrize("frame_id", ["", "i", "imu", "imu_link", "imu_link_0", "é" * 5, "éé", "x" * 31])
def test_imu_is_sized_exactly(frame_id: str) -> None:
    imu = Imu()
    imu.header.frame_id = frame_id
    assert payload_size(imu) == len(serialize_message(imu))
