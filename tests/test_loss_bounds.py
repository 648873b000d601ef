"""The crash loss bound: a message received more than ``storage.flush_interval`` ago is a complete record in
the file, whatever happens to the process next. Real container processes, killed with SIGKILL; the files are
read as the kill left them (no finalization, no repair), with mcap's stream reader and sqlite3.

A 5 Hz IMU fills no 768 KiB MCAP chunk and no SQLite batch in seconds: without time-based flushing, nothing of
it would be in the file after the kill.
"""
from __future__ import annotations

import pathlib
import random
import sqlite3
import struct
import time

import pytest
from mcap.stream_reader import StreamReader
from mcap.records import Channel, Message
from rosbags.typesys import Stores, get_typestore

from container_process import Containers, wait_until

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
IMU_RATE = 5.0
FLUSH_INTERVAL = 1.0


def imu_stamps_in_mcap(path: pathlib.Path) -> list[float]:
    """Header stamps (s) of the IMU messages in the complete records of a possibly cut MCAP file."""
    stamps: list[float] = []
    channels: dict[int, str] = {}
    with open(path, "rb") as stream:
        try:
            for record in StreamReader(stream).records:
                if isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message) and channels.get(record.channel_id) == "/imu/imu":
                    stamps.append(_stamp(bytes(record.data)))
        except Exception:  # noqa: BLE001 - the cut: everything before it has been read
            pass
    return stamps


def imu_stamps_in_sqlite(path: pathlib.Path) -> list[float]:
    """Header stamps (s) of the IMU rows a crashed SQLite3 bag holds (sqlite rolls back what was in flight)."""
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
        rows = db.execute("SELECT data FROM messages JOIN topics ON topics.id = messages.topic_id "
                          "WHERE topics.name = '/imu/imu' ORDER BY messages.id").fetchall()
    return [_stamp(bytes(data)) for (data,) in rows]


def _stamp(cdr: bytes) -> float:
    sec, nanosec = struct.unpack_from("<iI", cdr, 4)  # header.stamp right after the encapsulation header
    return sec + nanosec * 1e-9


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_killed_recorder_has_every_message_older_than_the_flush_interval(
        containers: Containers, tmp_path: pathlib.Path, storage: str) -> None:
    seed = random.randrange(1_000_000)
    print(f"loss-bound seed {seed}")
    process, client = containers.start("--use-intra-process-comms")
    assert client.load("components::ImuDriver", parameters={"rate": IMU_RATE}).success
    uri = tmp_path / "killed_bag"
    recorder = client.load("components::Recorder", parameters={
        "storage.uri": str(uri), "storage.storage_id": storage, "record.topics": ["/imu/imu"],
        "storage.flush_interval": FLUSH_INTERVAL})
    assert recorder.success, recorder
    time.sleep(2.0 + random.Random(seed).uniform(0.0, 2.0))  # a random moment of steady recording
    process.process.kill()
    killed = time.time()
    process.process.wait()
    files = sorted(uri.glob(f"*.{'mcap' if storage == 'mcap' else 'db3'}"))
    assert len(files) == 1 and not (uri / "metadata.yaml").exists()  # a crash: nothing was finalized
    stamps = (imu_stamps_in_mcap if storage == "mcap" else imu_stamps_in_sqlite)(files[0])
    assert stamps, "nothing of the recording reached the file"
    first = stamps[0]
    due = [first + i / IMU_RATE for i in range(int((killed - FLUSH_INTERVAL - 0.05 - first) * IMU_RATE) + 1)]
    assert len(stamps) >= len(due), (f"{len(due)} messages were received more than {FLUSH_INTERVAL} s before "
                                     f"the kill, the file holds {len(stamps)}")
    assert stamps == sorted(set(stamps)), "a message is in the file twice or out of order"
    assert wait_until(lambda: not process.alive(), 5.0)
