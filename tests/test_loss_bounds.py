"""The crash loss bound: a message received more than ``storage.flush_interval`` ago is a complete record in
the file, whatever happens to the process next. Real container processes, killed with SIGKILL; the files are
read as the kill left them (no finalization, no repair), with mcap's stream reader and sqlite3.

A 5 Hz IMU fills no 768 KiB MCAP chunk and no SQLite batch in seconds: without time-based flushing, nothing of
it would be in the file after the kill. "Older than the flush interval" is told by sequence numbers: the file must
reach the newest IMU message a plain subscriber in the test process had received a flush interval (plus a margin)
before the kill. The kill comes at a seeded random moment: a fixed seed by default, fresh ones with
``make sweep``; the seed is printed and ``IPC_LOSS_SEED`` replays it.
"""
from __future__ import annotations

import contextlib
import os
import pathlib
import random
import sqlite3

import pytest
from mcap.stream_reader import StreamReader
from mcap.records import Channel, Message
from rclpy.node import Node
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import Imu

from container_process import Containers, wait_until
from ipc_testing import spin_for

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
IMU_RATE = 5.0
FLUSH_INTERVAL = 1.0
MARGIN = 0.5  # beyond the flush interval: the recorder, in the driver's process, had the message first
DEFAULT_SEED = 4_242


def imu_sequences_in_mcap(path: pathlib.Path) -> list[int]:
    """Sequence numbers of the IMU messages in the complete records of a possibly cut MCAP file."""
    stamps: list[int] = []
    channels: dict[int, str] = {}
    with open(path, "rb") as stream:
        try:
            for record in StreamReader(stream).records:
                if isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message) and channels.get(record.channel_id) == "/imu/imu":
                    stamps.append(_sequence(bytes(record.data)))
        except Exception:  # noqa: BLE001 - the cut: everything before it has been read
            pass
    return stamps


def imu_sequences_in_sqlite(path: pathlib.Path) -> list[int]:
    """Sequence numbers of the IMU rows a crashed SQLite3 bag holds. Opened read-write, as ``bag recover`` or the
    sqlite3 shell would: a kill in the middle of a commit leaves a hot journal, which sqlite rolls back on opening
    (``mode=ro`` refuses it with SQLITE_READONLY_ROLLBACK)."""
    with contextlib.closing(sqlite3.connect(path)) as db:
        rows = db.execute("SELECT data FROM messages JOIN topics ON topics.id = messages.topic_id "
                          "WHERE topics.name = '/imu/imu' ORDER BY messages.id").fetchall()
    return [_sequence(bytes(data)) for (data,) in rows]


def _sequence(cdr: bytes) -> int:
    """The ImuDriver's sequence number: orientation_covariance[1], decoded by rosbags."""
    return int(TYPESTORE.deserialize_cdr(cdr, "sensor_msgs/msg/Imu").orientation_covariance[1])


def kill_and_read(containers: Containers, probe: Node, tmp_path: pathlib.Path, storage: str, seed: int) -> None:
    print(f"IPC_LOSS_SEED={seed}")
    live: list[int] = []
    probe.create_subscription(Imu, "/imu/imu", lambda msg: live.append(int(msg.orientation_covariance[1])), 10)
    process, client = containers.start("--use-intra-process-comms")
    assert client.load("components::ImuDriver", parameters={"rate": IMU_RATE}).success
    uri = tmp_path / "killed_bag"
    recorder = client.load("components::Recorder", parameters={
        "storage.uri": str(uri), "storage.storage_id": storage, "record.topics": ["/imu/imu"],
        "storage.flush_interval": FLUSH_INTERVAL})
    assert recorder.success, recorder
    assert spin_for(probe, 20.0, lambda: bool(live)), "no IMU message arrived"
    spin_for(probe, 1.0 + random.Random(seed).uniform(0.0, 2.0))  # a random moment of steady recording
    older = max(live)  # the newest message the test has: older than the flush interval at the kill
    spin_for(probe, FLUSH_INTERVAL + MARGIN)
    process.process.kill()
    process.process.wait()
    files = sorted(uri.glob(f"*.{'mcap' if storage == 'mcap' else 'db3'}"))
    assert len(files) == 1 and not (uri / "metadata.yaml").exists()  # a crash: nothing was finalized
    seqs = (imu_sequences_in_mcap if storage == "mcap" else imu_sequences_in_sqlite)(files[0])
    assert seqs, "nothing of the recording reached the file"
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "a message is missing, twice or out of order"
    assert seqs[-1] >= older, (f"the file ends at IMU message {seqs[-1]}; the test had received message {older} "
                               f"more than the flush interval ({FLUSH_INTERVAL} s) before the kill")
    assert wait_until(lambda: not process.alive(), 5.0)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_killed_recorder_has_every_message_older_than_the_flush_interval(
        containers: Containers, probe: Node, tmp_path: pathlib.Path, storage: str) -> None:
    kill_and_read(containers, probe, tmp_path, storage, int(os.environ.get("IPC_LOSS_SEED") or DEFAULT_SEED))


@pytest.mark.sweep
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_recorder_killed_at_random_moments_has_every_message_older_than_the_flush_interval(
        containers: Containers, probe: Node, tmp_path: pathlib.Path, storage: str) -> None:
    seed = int(os.environ.get("IPC_LOSS_SEED") or random.randrange(1_000_000))
    kill_and_read(containers, probe, tmp_path, storage, seed)
