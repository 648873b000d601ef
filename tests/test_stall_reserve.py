"""A disk that stalls for longer than the cache lasts: the recorder keeps accepting messages into its stall
reserve (``storage.stall_reserve``) instead of dropping them, shows the backlog live, and writes everything once
the disk comes back. With no reserve (rosbag2's behaviour) the same stall drops frames, counted as cache_full.

In-process: a container's manager, a camera driver and a recorder whose bag writer blocks while a test-owned
event is clear, all delivering intra-process; the bag is read back with rosbags (sequence numbers in the
frames' first 8 bytes).
"""
from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Any, Iterator

import pytest
from rosbags.rosbag2 import Reader

from baglib.format.cdr_fast import CdrData
from baglib.write.writer import BagWriter
from component_container.component_manager import ComponentManager
from component_container.health import WARN
from component_container.startup_file import load_request
from components.recorder.message_cache import CachedMessage, MessageCache
from components.recorder.recorder import Recorder
from ipc_testing import wait_until
from ipc_testing.process_context import process_context

FRAME = {"width": 320, "height": 240, "fps": 30.0}          # 230 kB frames, ~7 MB/s
CACHE = 1024 * 1024                                          # a cache that lasts ~0.15 s of this camera


class StallingBagWriter(BagWriter):
    """A bag on a disk that stalls while :data:`DISK_UP` is clear (a write blocks, as one stuck in the kernel)."""

    DISK_UP = threading.Event()

    def write(self, topic: str, data: CdrData, log_time_ns: int, publish_time_ns: int,
              split: bool | None = None) -> None:
        self.DISK_UP.wait()
        super().write(topic, data, log_time_ns, publish_time_ns, split)


class StallingRecorder(Recorder):
    writer_class = StallingBagWriter


@pytest.fixture(params=[10.0])
def manager(request: pytest.FixtureRequest) -> Iterator[ComponentManager]:
    """An in-process container; its shutdown timeout (the recorder's bound on finishing a bag) is the param."""
    manager = ComponentManager("single", use_intra_process_comms=True, allow_module_plugins=True,
                               node_name="stall_reserve_test", context=process_context(),
                               shutdown_timeout=request.param)
    StallingBagWriter.DISK_UP.set()
    try:
        yield manager
    finally:
        StallingBagWriter.DISK_UP.set()
        manager.shutdown()
        manager.destroy_node()


def load(manager: ComponentManager, plugin: str, package: str, **parameters: Any) -> Any:
    return manager.load(load_request({"package": package, "plugin": plugin, "parameters": parameters}, 1))


def sequences(bag: Path) -> list[int]:
    with Reader(bag) as reader:
        return [int.from_bytes(raw[-FRAME["width"] * FRAME["height"] * 3:][:8], "little")
                for _, _, raw in reader.messages()]


def record_through_a_stall(manager: ComponentManager, bag: Path, reserve: int) -> dict[str, Any]:
    """Record the camera while the disk stalls until the backlog is 8 cache sizes; returns the final stats."""
    loaded = load(manager, "test_stall_reserve:StallingRecorder", "test_stall_reserve", **{
        "storage.uri": str(bag), "storage.max_cache_size": CACHE, "storage.stall_reserve": reserve,
        "record.topics": ["/camera/image_raw"]})
    recorder = loaded.node
    StallingBagWriter.DISK_UP.clear()
    camera = load(manager, "components::CameraDriver", "components", **FRAME)

    def received() -> int:
        current = recorder.stats()["current"]
        return sum(topic["received"] for topic in current["topics"].values())

    frames_for_8_caches = 8 * CACHE // (FRAME["width"] * FRAME["height"] * 3) + 1
    assert wait_until(lambda: received() >= frames_for_8_caches, 30.0), recorder.stats()
    live = recorder.stats()["current"]
    health = recorder.health()
    StallingBagWriter.DISK_UP.set()
    manager.unload(camera.unique_id)
    returns = 1 if reserve else 0  # a backlog in the reserve gives its memory back once it has drained

    def drained() -> bool:
        current = recorder.stats()["current"]
        return current["backlog_bytes"] == 0 and current["memory_returns"] == returns

    assert wait_until(drained, 30.0), recorder.stats()
    final = recorder.stats()["current"]
    manager.unload(loaded.unique_id)
    return {"live": live, "health": health, "final": final}


def test_a_stall_longer_than_the_cache_fills_the_reserve_and_loses_nothing(manager: ComponentManager,
                                                                          tmp_path: Path) -> None:
    result = record_through_a_stall(manager, tmp_path / "bag", reserve=64 * 1024 * 1024)
    live, final = result["live"], result["final"]
    assert live["backlog_bytes"] > CACHE and live["reserve_in_use_bytes"] == live["backlog_bytes"] - CACHE
    assert live["backlog_s"] > 0 and live["memory_return_pending"]
    assert not final["memory_return_pending"] and final["memory_returns"] == 1
    assert result["health"].level == WARN and "writer behind" in result["health"].message
    topic = final["topics"]["/camera/image_raw"]
    assert topic["dropped"] == 0 and topic["written"] == topic["received"], final
    assert final["peak_backlog_bytes"] >= live["backlog_bytes"]
    recorded = sequences(tmp_path / "bag")
    assert recorded == list(range(recorded[0], recorded[0] + len(recorded)))  # none missing, none twice
    assert len(recorded) == topic["written"]


def test_without_a_reserve_the_same_stall_drops_frames(manager: ComponentManager, tmp_path: Path) -> None:
    result = record_through_a_stall(manager, tmp_path / "bag", reserve=0)
    final = result["final"]
    assert final["drop_reasons"]["/camera/image_raw"]["cache_full"] > 0
    assert final["topics"]["/camera/image_raw"]["written"] + final["topics"]["/camera/image_raw"]["dropped"] \
        == final["topics"]["/camera/image_raw"]["received"]


def test_the_cache_fills_its_reserve_before_it_drops() -> None:
    cache = MessageCache(max_bytes=1000, reserve=500)
    accepted = [cache.push(CachedMessage("/t", b"", 100, n, n)) for n in range(16)]
    assert accepted == [True] * 15 + [False]
    assert cache.dropped == {"/t": 1} and cache.peak_bytes == 1500
    assert cache.backlog() == (1500, 0)  # bytes held, log time of the oldest queued message
    taken = cache.take_all(timeout=0)
    assert cache.backlog() == (1500, None)  # taken by the writer, not yet written: still held
    cache.release(sum(message.size for message in taken))
    assert cache.backlog() == (0, None)


def test_a_snapshot_ring_has_no_reserve() -> None:
    ring = MessageCache(max_bytes=1000, ring=True, reserve=500)
    for n in range(15):
        ring.push(CachedMessage("/t", b"", 100, n, n))
    assert ring.bytes == 1000 and ring.evicted == {"/t": 5}


@pytest.mark.parametrize("manager", [0.5], indirect=True)
def test_a_writer_given_up_on_closes_the_bag_when_it_gets_to_its_end(manager: ComponentManager,
                                                                       tmp_path: Path) -> None:
    """Stopping the recorder on a stalled disk gives up on the writer after 80 % of the shutdown timeout; when
    the disk comes back, the writer finishes its batch and closes the bag: finalized, its file closed (the
    container does not keep a descriptor per stalled recording)."""
    bag = tmp_path / "bag"
    loaded = load(manager, "test_stall_reserve:StallingRecorder", "test_stall_reserve", **{
        "storage.uri": str(bag), "record.topics": ["/camera/image_raw"]})
    recorder = loaded.node
    camera = load(manager, "components::CameraDriver", "components", **FRAME)
    topics = lambda: recorder.stats()["current"]["topics"]  # noqa: E731
    assert wait_until(lambda: topics().get("/camera/image_raw", {}).get("written", 0) >= 3, 10.0)
    StallingBagWriter.DISK_UP.clear()
    # a frame queued (backlog_s counts from the oldest one), which the writer must write before it can end;
    # backlog_bytes alone also counts frames written whose room is not released yet
    assert wait_until(lambda: recorder.stats()["current"]["backlog_s"] > 0, 10.0)
    final = recorder.stop_recording()
    assert "did not finish" in final["error"] and not (bag / "metadata.yaml").exists()
    StallingBagWriter.DISK_UP.set()
    assert wait_until(lambda: (bag / "metadata.yaml").exists(), 10.0)

    def open_in_bag() -> list[str]:
        fds = Path("/proc/self/fd")
        return [target for target in (os.readlink(fd) for fd in fds.iterdir() if fd.exists()) if str(bag) in target]

    assert wait_until(lambda: not open_in_bag(), 5.0), open_in_bag()
    assert len(sequences(bag)) >= 3  # rosbags reads it as it is, no repair needed
    manager.unload(camera.unique_id)
    manager.unload(loaded.unique_id)

