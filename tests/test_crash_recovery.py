"""SIGKILL at random moments while the rig is recorded, then ``ipc-component bag recover``, as a user would.

Each round starts a container with a camera (320x240 @ 30 Hz) and an IMU (200 Hz) and a recorder next to them
(MCAP or SQLite3, with or without splitting into ~2 MB files), kills the container with SIGKILL at a random
moment, recovers the bag with the CLI and reads it with rosbags and (MCAP) the mcap seeking reader. Every
message published more than ``storage.flush_interval`` before the kill must be there, none twice: per topic
the recorded sequence numbers are one unbroken run that reaches to within the flush interval of the kill.
Seeded (``IPC_CRASH_SEED`` replays a run); the seed is printed.
"""
from __future__ import annotations

import os
import pathlib
import random
import struct
import subprocess
import sys
import time

import pytest
import yaml
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from container_process import Containers

ROUNDS = 20
FLUSH_INTERVAL = 1.0
RATES = {"/camera/image_raw": 30.0, "/imu/imu": 200.0}
CONFIGS = [("mcap", 0), ("sqlite3", 0), ("mcap", 2 * 1024 * 1024), ("sqlite3", 2 * 1024 * 1024)]
CLI = pathlib.Path(sys.executable).with_name("ipc-component")
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def sequence_and_stamp(topic: str, msgtype: str, cdr: bytes) -> tuple[int, float]:
    """The driver's sequence number (Imu orientation_covariance[1], Image data[0:8]) and the header stamp."""
    msg = TYPESTORE.deserialize_cdr(cdr, msgtype)
    stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
    if topic == "/imu/imu":
        return int(msg.orientation_covariance[1]), stamp
    return struct.unpack_from("<Q", bytes(msg.data[:8]))[0], stamp


def read_recovered(uri: pathlib.Path, storage: str) -> dict[str, list[tuple[int, float]]]:
    found: dict[str, list[tuple[int, float]]] = {topic: [] for topic in RATES}
    with Reader(uri) as reader:
        for connection, _, raw in reader.messages():
            if connection.topic in found:
                found[connection.topic].append(sequence_and_stamp(connection.topic, connection.msgtype, raw))
    if storage == "mcap":
        listed = yaml.safe_load((uri / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        for path in [uri / name for name in listed["relative_file_paths"]]:
            with open(path, "rb") as stream:
                mcap = make_reader(stream)
                assert mcap.get_summary() is not None, f"{path.name}: no summary after recover"
                sum(1 for _ in mcap.iter_messages())
    return found


@pytest.mark.parametrize("round_", range(ROUNDS))
def test_sigkill_then_recover_keeps_everything_older_than_the_flush_interval(
        containers: Containers, tmp_path: pathlib.Path, round_: int) -> None:
    seed = int(os.environ.get("IPC_CRASH_SEED", random.randrange(1_000_000)))
    print(f"crash-recovery seed {seed} (round {round_})")
    rng = random.Random(seed)
    storage, split = CONFIGS[round_ % len(CONFIGS)]
    process, client = containers.start("--use-intra-process-comms")
    assert client.load("components::CameraDriver", parameters={"width": 320, "height": 240}).success
    assert client.load("components::ImuDriver", parameters={"rate": 200.0}).success
    uri = tmp_path / "killed"
    recorder = client.load("components::Recorder", parameters={
        "storage.uri": str(uri), "storage.storage_id": storage, "storage.max_bagfile_size": split,
        "storage.flush_interval": FLUSH_INTERVAL, "record.topics": list(RATES)})
    assert recorder.success, recorder
    time.sleep(rng.uniform(1.5, 4.0))
    process.process.kill()
    killed = time.time()
    process.process.wait()
    recovered = subprocess.run([str(CLI), "bag", "recover", str(uri)], capture_output=True, text=True,
                               timeout=120)
    assert recovered.returncode == 0, recovered.stdout + recovered.stderr
    print(recovered.stdout)
    found = read_recovered(uri, storage)
    for topic, rate in RATES.items():
        seqs = [seq for seq, _ in found[topic]]
        assert seqs, f"{topic}: nothing recovered"
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), f"{topic}: a gap or a duplicate"
        last_stamp = max(stamp for _, stamp in found[topic])
        assert last_stamp >= killed - FLUSH_INTERVAL - 1.0 / rate - 0.1, (
            f"{topic}: the newest recovered message is {killed - last_stamp:.2f} s older than the kill "
            f"(flush interval {FLUSH_INTERVAL} s)")
