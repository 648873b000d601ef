"""Round-trip fidelity: record the rig, play the bag into a second container that records it again.

Container A runs the drivers (camera, LiDAR, IMU) with a recorder next to them, all intra-process. Container B
runs a recorder and then a player of A's bag, both intra-process: the recorder gets the player's message
objects by reference and serializes them itself. Read back by ``rosbags`` (an independent reader), the two bags
must hold per topic the same message bytes in the same order, and B's log times (when its recorder received
each message, i.e. when the player published it) must keep A's offsets between messages: the bag's schedule.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import yaml
from rosbags.rosbag2 import Reader

from container_process import Containers, wait_until

IPC = {"use_intra_process_comms": True}
TOPICS = ["/camera/image_raw", "/camera/camera_info", "/lidar/points", "/imu/imu"]
RIG = [
    ("components::CameraDriver", "camera", {"width": 320, "height": 240, "fps": 30.0}),
    ("components::LidarDriver", "lidar", {"points_per_scan": 4096, "rings": 16, "rate": 10.0}),
    ("components::ImuDriver", "imu", {"rate": 200.0}),
]
#: The issue's bound on the offset between consecutive messages, asserted for 95 % of them on top of what this
#: machine's own clock achieves in the same run: on this 2-core VM the hypervisor takes the CPU away for up to
#: 8 ms at a time (a busy loop sees it), so a lone thread sleeping to the bag's schedule already misses it by a
#: p95 of 1.4-3.2 ms. The player's p99 against that floor is the open part of issue 10, in
#: benchmarks/replay_bench.py. Both distributions are printed.
OFFSET_BOUND_MS = 2.0


def read(bag: Path) -> dict[str, list[tuple[int, bytes]]]:
    """topic -> [(log time, CDR)] in bag order, by rosbags."""
    messages: dict[str, list[tuple[int, bytes]]] = {topic: [] for topic in TOPICS}
    with Reader(bag) as reader:
        for connection, timestamp, data in reader.messages():
            messages[connection.topic].append((timestamp, bytes(data)))
    return messages


def offset_errors(first: list[int], second: list[int]) -> list[float]:
    """|offset in second - offset in first| in ms for every pair of consecutive times, sorted."""
    return sorted(abs((b2 - b1) - (a2 - a1)) / 1e6
                  for a1, a2, b1, b2 in zip(first, first[1:], second, second[1:]))


def quantiles(errors: list[float]) -> str:
    return (f"p50 {errors[len(errors) // 2]:.3f} ms, p95 {errors[int(0.95 * len(errors))]:.3f} ms, "
            f"p99 {errors[int(0.99 * len(errors))]:.3f} ms, max {errors[-1]:.3f} ms")


class ClockFloor(threading.Thread):
    """A plain thread of this process sleeping to the same schedule while the player plays (sleep, then poll
    the last 0.3 ms), publishing nothing: the offset errors this machine imposes on any sleeper in the same
    minutes. Deliberately none of the player's code, so a slower player clock cannot hide in its own floor."""

    def __init__(self, schedule: list[int], delay_s: float) -> None:
        super().__init__(daemon=True)
        self.schedule, self.woke = schedule, []
        self.start_ns = time.monotonic_ns() + int(delay_s * 1e9)

    def run(self) -> None:
        for due in self.schedule:
            deadline = self.start_ns + due - self.schedule[0]
            remaining = deadline - time.monotonic_ns()
            if remaining > 300_000:
                time.sleep((remaining - 300_000) / 1e9)
            while time.monotonic_ns() < deadline:
                pass
            self.woke.append(time.monotonic_ns())


def record(client: Any, name: str, uri: Path) -> int:
    response = client.load("components::Recorder", name=name, extra=IPC,
                           parameters={"storage.uri": str(uri), "record.topics": TOPICS})
    assert response.success, response.error_message
    return response.unique_id


def test_record_play_record_keeps_bytes_order_and_offsets(probe: Any, tmp_path: Path) -> None:
    rig_file = tmp_path / "rig.yaml"
    rig_file.write_text(yaml.safe_dump({"components": [
        {"package": "components", "plugin": plugin, "name": name, "parameters": parameters,
         "extra_arguments": IPC} for plugin, name, parameters in RIG]}))
    started = Containers(probe)
    try:
        rig_process, rig = started.start("--load", str(rig_file), "--ros-args", "-r", "__node:=rig", container="/rig")
        assert wait_until(lambda: len(rig.list().unique_ids) == 3, 20.0)
        first = tmp_path / "first"
        recorder = record(rig, "recorder", first)
        time.sleep(3.0)
        assert rig.unload(recorder).success
        assert rig_process.stop() == 0  # its drivers would publish on the topics the player replays

        _, replay = started.start("--use-intra-process-comms", "--ros-args", "-r", "__node:=replay", container="/replay")
        second = tmp_path / "second"
        recorder = record(replay, "rerecorder", second)
        player = replay.load("components::Player", name="player", extra=IPC,
                             parameters={"storage.uri": str(first), "play.delay.sec": 1})
        assert player.success, player.error_message
        original = read(first)
        schedule = sorted(t for messages in original.values() for t, _ in messages)
        floor = ClockFloor(schedule, delay_s=1.0)
        floor.start()
        time.sleep(1.0 + (schedule[-1] - schedule[0]) / 1e9 + 1.0)
        floor.join(timeout=10.0)
        assert replay.unload(player.unique_id).success
        assert replay.unload(recorder).success
    finally:
        started.close()

    again = read(second)
    for topic in TOPICS:
        assert len(original[topic]) > 10, topic
        assert [data for _, data in again[topic]] == [data for _, data in original[topic]], topic
    # Offsets between consecutive messages of the whole bag (log-time order) against the original's.
    first_order = sorted((t, topic, i) for topic in TOPICS for i, (t, _) in enumerate(original[topic]))
    errors = offset_errors([t for t, _, _ in first_order], [again[topic][i][0] for _, topic, i in first_order])
    assert len(floor.woke) == len(schedule), "the clock floor did not finish"
    machine = offset_errors(schedule, floor.woke)
    print(f"offset error over {len(errors)} consecutive pairs: {quantiles(errors)}; "
          f"this machine's clock floor in the same run: {quantiles(machine)}")
    p95, floor_p95 = errors[int(0.95 * len(errors))], machine[int(0.95 * len(machine))]
    assert p95 <= OFFSET_BOUND_MS + floor_p95, errors[-20:]
