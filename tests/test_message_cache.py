"""The recorder's cache bound is honest: every message counts for what it serializes to, not for a ``data`` field.

Real message objects of the types a robot records besides images and clouds (scans, markers, paths, pose
arrays), sized against rclpy's own serialization.
"""
from __future__ import annotations

import threading
import time
from typing import Any, Callable

import pytest
from geometry_msgs.msg import Pose, PoseArray, PoseStamped
from nav_msgs.msg import Path
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image, Imu, LaserScan
from visualization_msgs.msg import Marker, MarkerArray

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


def _push_later(cache: MessageCache, delays: list[float], size: int = 100) -> threading.Thread:
    def run() -> None:
        for delay in delays:
            time.sleep(delay)
            cache.push(_message(size))
    thread = threading.Thread(target=run)
    thread.start()
    return thread


def test_take_all_lets_a_batch_gather() -> None:
    """The writer is woken once for messages that arrive within ``gather`` of its previous take, not per message."""
    cache = MessageCache(max_bytes=1 << 20)
    assert cache.take_all(timeout=0.0) == []  # the previous take
    pusher = _push_later(cache, [0.01] * 5)
    batch = cache.take_all(timeout=5.0, gather=1.0)
    pusher.join()
    assert len(batch) == 5


def test_take_all_stops_gathering_at_a_quarter_of_the_cache_or_a_close() -> None:
    """Gathering never risks a drop that taking at once would avoid, and never delays the final flush."""
    cache = MessageCache(max_bytes=4000)
    cache.take_all(timeout=0.0)
    start = time.monotonic()
    pusher = _push_later(cache, [0.01, 0.01], size=600)  # 1200 bytes: past a quarter of 4000
    batch = cache.take_all(timeout=60.0, gather=60.0)
    pusher.join()
    assert len(batch) == 2 and time.monotonic() - start < 30.0
    closer = threading.Thread(target=lambda: (time.sleep(0.05), cache.close()))
    cache.push(_message())
    closer.start()
    batch = cache.take_all(timeout=60.0, gather=60.0)
    closer.join()
    assert len(batch) == 1 and cache.closed and time.monotonic() - start < 30.0


@pytest.mark.parametrize("frame_id", ["", "i", "imu", "imu_link", "imu_link_0", "é" * 5, "éé", "x" * 31])
def test_imu_is_sized_exactly(frame_id: str) -> None:
    imu = Imu()
    imu.header.frame_id = frame_id
    assert payload_size(imu) == len(serialize_message(imu))
