"""An existing distributed engine reads what was uploaded (issue 36, item 6): Ray Data's ``read_mcap``.

Two MCAP bags of real CDR messages (camera frames and an IMU, written with this project's BagWriter, one of them
split into several files) are uploaded under one prefix with ``upload_bags`` (what ``bag upload`` and the
recorder's upload process run) to a real nanio server on loopback. Ray Data then reads the prefix through
pyarrow's S3 filesystem, as a cluster would read a fleet's bucket: its message count per topic must equal what
``ipc-component bag info`` says of the bags in the store; with topic pushdown it reads one topic only, and with a
time-range pushdown exactly the messages of that range.

Ray is not a dependency of ``make test``: ``make sweep`` installs the ``cluster`` extra and runs this test. Run
without Ray, it fails saying how to install it (a sweep that silently skipped it would check nothing).
"""
from __future__ import annotations

import collections
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from baglib.read.reader import BagReader
from baglib.upload.bag_upload import upload_bags
from baglib.upload.location import parse_s3_uri
from ipc_testing.camera_bag import IMU_TOPIC, T0, camera_topic, write_camera_bag
from ipc_testing.s3_server import ACCESS_KEY, SECRET_KEY, S3Server
from upload_harness import bucket, s3  # noqa: F401  (fixtures)

pytestmark = pytest.mark.sweep

IPC_COMPONENT = shutil.which("ipc-component", path=str(Path(sys.executable).parent)) or "ipc-component"
PREFIX = "fleet"
#: Frames per camera of each bag; the second bag starts a minute after the first.
FRAMES = 45
SECOND_BAG_START = T0 + 60 * 10**9
#: A time range inside the first bag, its ends between two messages of every topic (cameras at 30 Hz, IMU at
#: 200 Hz), so whether an end is inclusive does not matter.
TIME_RANGE = (T0 + 334_000_000, T0 + 1_001_000_000)


def info_counts(server: S3Server, uri: str) -> dict[str, int]:
    """Messages per topic, as ``ipc-component bag info`` prints them for the bag at ``uri`` in ``server``."""
    done = subprocess.run([IPC_COMPONENT, "bag", "info", "--endpoint-url", server.endpoint_url, uri],
                          capture_output=True, text=True, timeout=60, env=dict(os.environ))
    assert done.returncode == 0, done.stderr
    return {name: int(count) for name, count in re.findall(r"Topic: (\S+) \| Type: \S+ \| Count: (\d+)", done.stdout)}


def local_counts(bags: list[Path], start_ns: int, stop_ns: int) -> dict[str, int]:
    """Messages per topic with ``start_ns <= log time < stop_ns`` in the local bags."""
    counts: collections.Counter[str] = collections.Counter()
    for bag in bags:
        with BagReader(bag) as reader:
            counts.update(message.connection.topic for message in reader.messages(start_ns=start_ns, stop_ns=stop_ns))
    return dict(counts)


@pytest.fixture()
def ray_session() -> Iterator[Any]:
    """Ray with few CPUs (the machine has two), no dashboard; shut down after the test."""
    try:
        import ray
        import ray.data  # noqa: F401
    except ImportError as error:
        pytest.fail(f"Ray is not installed ({error}): the sweep needs the 'cluster' extra, "
                    "pip install -e '.[cluster]' (make sweep installs it)", pytrace=False)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield ray
    finally:
        ray.shutdown()


def ray_counts(ray: Any, server: S3Server, bucket: str, **pushdown: Any) -> dict[str, int]:
    """Messages per topic that Ray Data's read_mcap finds under ``bucket``/PREFIX/ (``pushdown``: topics,
    time_range)."""
    import pyarrow.fs
    filesystem = pyarrow.fs.S3FileSystem(endpoint_override=f"127.0.0.1:{server.port}", scheme="http",
                                         access_key=ACCESS_KEY, secret_key=SECRET_KEY, region="us-east-1")
    dataset = ray.data.read_mcap(f"{bucket}/{PREFIX}/", filesystem=filesystem, **pushdown)
    return {row["topic"]: row["count()"] for row in dataset.groupby("topic").count().take_all()}


def test_ray_data_reads_the_uploaded_bags_with_the_counts_of_bag_info(s3: S3Server, bucket: str, tmp_path: Path,
                                                                      ray_session: Any) -> None:
    bags = [tmp_path / "robot_a", tmp_path / "robot_b"]
    written = [write_camera_bag(bags[0], FRAMES, width=320, height=240, max_bagfile_size=2 << 20),
               write_camera_bag(bags[1], FRAMES, width=320, height=240, start_ns=SECOND_BAG_START)]
    assert len(list(bags[0].glob("*.mcap"))) > 1  # one bag split into several files
    upload_bags(bags, parse_s3_uri(f"s3://{bucket}/{PREFIX}"), s3.endpoint_url)

    in_store = [info_counts(s3, f"s3://{bucket}/{PREFIX}/{bag.name}") for bag in bags]
    assert in_store == written
    expected = dict(collections.Counter(in_store[0]) + collections.Counter(in_store[1]))
    assert ray_counts(ray_session, s3, bucket) == expected

    cameras = {camera_topic(0), camera_topic(1)}
    assert ray_counts(ray_session, s3, bucket, topics=cameras) == {topic: expected[topic] for topic in cameras}
    assert ray_counts(ray_session, s3, bucket, topics=[IMU_TOPIC]) == {IMU_TOPIC: expected[IMU_TOPIC]}

    in_range = local_counts(bags, *TIME_RANGE)
    assert in_range == {camera_topic(0): 20, camera_topic(1): 20, IMU_TOPIC: 134}
    assert ray_counts(ray_session, s3, bucket, time_range=TIME_RANGE) == in_range
