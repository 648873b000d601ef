"""Fuzzing the load path: thousands of random LoadNode / UnloadNode requests and recorder service calls
against a real container running a camera, an IMU and a recorder (see tests/fuzz_scene.py).

Afterwards the container is alive and answers ListNodes, the drivers publish at their rate, the recorder's
bag reads back, RSS grew by less than 10 MiB over the last third of the requests (the first two thirds
warm the container up), and nothing was written outside the bag root (the container's
fresh working directory is unchanged, and no file carrying the fuzz marker appeared in /tmp).

The seed is printed; ``IPC_FUZZ_SEED=<seed>`` replays a run and ``IPC_FUZZ_REQUESTS`` scales it (default
7500, about a minute and a half on 2 cores). benchmarks/fuzz_load.py runs the same scenario at 50 000 requests.
"""
from __future__ import annotations

import os
import pathlib
import signal
from typing import Iterator

import pytest
from rclpy.node import Node

from container_process import listing
from fuzz_scene import RATES, FuzzScene, environment_seed, file_listing, rss_bytes

TMP = pathlib.Path("/tmp")
RSS_GROWTH_LIMIT = 10 * 1024 * 1024  # over the last 2500 requests (see the test for what was measured)
RATE_SHARE = 0.5  # generous: a loaded 2-core machine, a plain rclpy subscriber in the test process


@pytest.fixture
def fuzz_node(ros: None) -> Iterator[Node]:
    """The node the pipelined calls go out from (an executor of its own, apart from the probe's)."""
    node = Node("_fuzz_requests")
    yield node
    node.destroy_node()


def test_random_requests_leave_the_container_healthy(probe: Node, fuzz_node: Node, tmp_path: pathlib.Path) -> None:
    seed = environment_seed()
    requests = int(os.environ.get("IPC_FUZZ_REQUESTS") or 7500)
    print(f"IPC_FUZZ_SEED={seed} IPC_FUZZ_REQUESTS={requests}")
    with FuzzScene(probe, tmp_path) as scene:
        cwd_before = file_listing(scene.cwd)
        tmp_before = scene.escaped(TMP)
        # The first two thirds warm up what a long-running container keeps (allocator arenas, DDS endpoint pools,
        # the recorder's bag machinery): RSS rises by 30-45 MiB and then levels off (+5 MiB over another 10 000
        # requests). After 2500 requests it had not yet: the next 2500 grew by 2.7 to 14.7 MiB, on the code
        # before and after one change alike; after 5000, the next 2500 grew by 1.7-2.3 MiB. A leak keeps
        # growing: the last third must stay under RSS_GROWTH_LIMIT (rclpy's type description service, switched
        # back on, grew by 13.4 MiB there: see README Known limitations).
        warm_up = scene.fuzz(seed, requests - requests // 3, fuzz_node)
        print(warm_up.summary())
        rss_before = rss_bytes(scene.process.pid)
        report = scene.fuzz(seed + 1, requests // 3, fuzz_node)
        print(report.summary())

        assert scene.process.alive(), scene.process.output
        assert sorted(name for _uid, name in listing(scene.client)) == sorted(scene.protected.values())
        rates = scene.message_rates()
        for topic, (_type, rate) in RATES.items():
            assert rates[topic] >= RATE_SHARE * rate, (seed, rates)
        growth = rss_bytes(scene.process.pid) - rss_before
        print(f"container RSS {rss_before / 2**20:.1f} MiB after the warm-up, grew by {growth / 2**20:.1f} MiB")
        assert growth < RSS_GROWTH_LIMIT, f"seed {seed}: RSS grew by {growth / 2**20:.1f} MiB in the last third"
        assert not warm_up.internal_errors + report.internal_errors, (seed, warm_up.internal_errors[:5],
                                                                      report.internal_errors[:5])

        scene.finish_recorder()
        bags = scene.bags()
        assert bags.get("baseline_bag", 0) > 0, (seed, bags)
        assert scene.process.stop(signal.SIGINT) == 0, scene.process.output
    assert file_listing(scene.cwd) == cwd_before, f"seed {seed}: written outside the bag root (cwd)"
    assert scene.escaped(TMP) == tmp_before, f"seed {seed}: written outside the bag root (/tmp)"
