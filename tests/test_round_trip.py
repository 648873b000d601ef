"""Round-trip fidelity: record the rig, play the bag into a second container that records it again.

Container A runs the drivers (camera, LiDAR, IMU) with a recorder next to them, all intra-process. Container B
runs a recorder and then a player of A's bag, both intra-process: the recorder gets the player's message
objects by reference and serializes them itself. Read back by ``rosbags`` (an independent reader), the two bags
must hold per topic the same message bytes in the same order, and B's log times (when its recorder received
each message, i.e. when the player published it) must keep the order of A's schedule across topics: two
messages the bag has at least ``ORDER_GAP_NS`` apart are replayed in that order.

How closely the player keeps the offsets between messages is timing: it is measured (and bounded) by
benchmarks/replay_bench.py; this test prints the distribution of the offset errors only.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from rosbags.rosbag2 import Reader

from container_process import Containers, wait_until, written

IPC = {"use_intra_process_comms": True}
TOPICS = ["/camera/image_raw", "/camera/camera_info", "/lidar/points", "/imu/imu"]
RIG = [
    ("components::CameraDriver", "camera", {"width": 320, "height": 240, "fps": 30.0}),
    ("components::LidarDriver", "lidar", {"points_per_scan": 4096, "rings": 16, "rate": 10.0}),
    ("components::ImuDriver", "imu", {"rate": 200.0}),
]
#: Messages of the bag at least this far apart (log time) must be replayed in their order.
ORDER_GAP_NS = 10_000_000
#: What the first recording holds at least, per topic (the LiDAR at 10 Hz takes longest).
MESSAGES_PER_TOPIC = 12


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


def record(client: Any, name: str, uri: Path) -> int:
    response = client.load("components::Recorder", name=name, extra=IPC,
                           parameters={"storage.uri": str(uri), "record.topics": TOPICS})
    assert response.success, response.error_message
    return response.unique_id


def test_record_play_record_keeps_bytes_order_and_schedule(probe: Any, tmp_path: Path) -> None:
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
        assert wait_until(lambda: all(written(probe, "/recorder", topic) >= MESSAGES_PER_TOPIC for topic in TOPICS),
                          60.0), "the rig's topics were not recorded"
        assert rig.unload(recorder).success
        assert rig_process.stop() == 0  # its drivers would publish on the topics the player replays

        _, replay = started.start("--use-intra-process-comms", "--ros-args", "-r", "__node:=replay", container="/replay")
        second = tmp_path / "second"
        recorder = record(replay, "rerecorder", second)
        original = read(first)
        player = replay.load("components::Player", name="player", extra=IPC,
                             parameters={"storage.uri": str(first), "play.delay.sec": 1})
        assert player.success, player.error_message
        assert wait_until(lambda: all(written(probe, "/rerecorder", topic) == len(original[topic])
                                      for topic in TOPICS), 120.0), "the replay was not recorded in full"
        assert replay.unload(player.unique_id).success
        assert replay.unload(recorder).success
    finally:
        started.close()

    again = read(second)
    for topic in TOPICS:
        assert len(original[topic]) >= MESSAGES_PER_TOPIC, topic
        assert [data for _, data in again[topic]] == [data for _, data in original[topic]], topic
    # The whole bag in log-time order, and when each of its messages was recorded again.
    first_order = sorted((t, topic, i) for topic in TOPICS for i, (t, _) in enumerate(original[topic]))
    scheduled = [t for t, _, _ in first_order]
    replayed = [again[topic][i][0] for _, topic, i in first_order]
    swapped = [(first_order[k][1:], first_order[k + 1][1:]) for k in range(len(scheduled) - 1)
               if scheduled[k + 1] - scheduled[k] >= ORDER_GAP_NS and replayed[k + 1] < replayed[k]]
    assert not swapped, f"replayed out of the bag's order: {swapped[:10]}"
    print(f"offset error over {len(scheduled) - 1} consecutive pairs: {quantiles(offset_errors(scheduled, replayed))}"
          " (bounded by benchmarks/replay_bench.py)")
