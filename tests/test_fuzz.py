"""Fuzzing the load path: random LoadNode / UnloadNode requests and recorder service calls against a real
container running a camera, an IMU and a recorder (see tests/fuzz_scene.py).

Afterwards the container is alive and answers ListNodes with only the scene's own components, the drivers still
publish (fresh, increasing sequence numbers reach a plain subscriber), no request hit an internal error, the
recorder's bag reads back, the container exits 0, and nothing was written outside the bag root (the container's
fresh working directory is unchanged, and no file carrying the fuzz marker appeared in /tmp).

The default run sends ``DEFAULT_REQUESTS`` requests of the fixed seed ``DEFAULT_SEED``. The sweep
(``make sweep``) sends 7500 requests of a fresh random seed and also bounds the RSS growth over the last third
of them (the first two thirds warm the container up). The seed is printed; ``IPC_FUZZ_SEED=<seed>`` replays a
run and ``IPC_FUZZ_REQUESTS`` scales it. The drivers' rates afterwards and runs of 50 000 requests are measured
by benchmarks/fuzz_load.py.
"""
from __future__ import annotations

import os
import pathlib
import signal
from typing import Iterator

import pytest
from rclpy.node import Node

from container_process import listing
from fuzz_scene import FuzzScene, environment_seed, file_listing, rss_bytes

TMP = pathlib.Path("/tmp")
RSS_GROWTH_LIMIT = 10 * 1024 * 1024  # over the last 2500 requests (see the sweep for what was measured)
DEFAULT_SEED = 20210621
DEFAULT_REQUESTS = 600
SWEEP_REQUESTS = 7500


@pytest.fixture
def fuzz_node(ros: None) -> Iterator[Node]:
    """The node the pipelined calls go out from (an executor of its own, apart from the probe's)."""
    node = Node("_fuzz_requests")
    yield node
    node.destroy_node()


def run_fuzz(probe: Node, fuzz_node: Node, workdir: pathlib.Path, seed: int, requests: int,
             rss_growth_limit: int | None) -> None:
    """The scene, ``requests`` requests of ``seed`` and every check afterwards. With ``rss_growth_limit`` the
    last third of the requests is sent after a measurement of the container's RSS and must grow it less."""
    print(f"IPC_FUZZ_SEED={seed} IPC_FUZZ_REQUESTS={requests}")
    with FuzzScene(probe, workdir) as scene:
        cwd_before = file_listing(scene.cwd)
        tmp_before = scene.escaped(TMP)
        if rss_growth_limit is None:
            reports = [scene.fuzz(seed, requests, fuzz_node)]
        else:
            # The first two thirds warm up what a long-running container keeps (allocator arenas, DDS endpoint
            # pools, the recorder's bag machinery): RSS rises for the first few thousand requests and then levels
            # off. A leak keeps growing: the last third must stay under the limit (rclpy's type description
            # service, switched back on, exceeds it: see docs/limitations.md).
            reports = [scene.fuzz(seed, requests - requests // 3, fuzz_node)]
            rss_before = rss_bytes(scene.process.pid)
            reports.append(scene.fuzz(seed + 1, requests // 3, fuzz_node))
        for report in reports:
            print(report.summary())

        assert scene.process.alive(), scene.process.output
        assert sorted(name for _uid, name in listing(scene.client)) == sorted(scene.protected.values())
        sequences = scene.fresh_sequences()
        for topic, seqs in sequences.items():  # still publishing, in order: the rates are the benchmark's
            assert len(seqs) >= 5 and seqs == sorted(set(seqs)), (seed, topic, seqs)
        if rss_growth_limit is not None:
            growth = rss_bytes(scene.process.pid) - rss_before
            print(f"container RSS {rss_before / 2**20:.1f} MiB after the warm-up, grew by {growth / 2**20:.1f} MiB")
            assert growth < rss_growth_limit, f"seed {seed}: RSS grew by {growth / 2**20:.1f} MiB in the last third"
        internal_errors = [error for report in reports for error in report.internal_errors]
        assert not internal_errors, (seed, internal_errors[:5])
        for report in reports:  # the container's own services answer every request, within LATE
            unanswered = {kind: (report.counts.abandoned.get(kind, 0), report.counts.late.get(kind, 0))
                          for kind in ("load", "unload")}
            assert unanswered == {"load": (0, 0), "unload": (0, 0)}, (seed, "(no reply, late)", unanswered)
        assert sum(report.loaded for report in reports) > 0, "no fuzz request loaded a component"

        scene.finish_recorder()
        bags = scene.bags()
        assert bags.get("baseline_bag", 0) > 0, (seed, bags)
        assert scene.process.stop(signal.SIGINT) == 0, scene.process.output
    assert file_listing(scene.cwd) == cwd_before, f"seed {seed}: written outside the bag root (cwd)"
    assert scene.escaped(TMP) == tmp_before, f"seed {seed}: written outside the bag root (/tmp)"


@pytest.mark.long
def test_random_requests_of_a_fixed_seed_leave_the_container_healthy(probe: Node, fuzz_node: Node,
                                                                     tmp_path: pathlib.Path) -> None:
    seed = int(os.environ.get("IPC_FUZZ_SEED") or DEFAULT_SEED)
    requests = int(os.environ.get("IPC_FUZZ_REQUESTS") or DEFAULT_REQUESTS)
    run_fuzz(probe, fuzz_node, tmp_path, seed, requests, rss_growth_limit=None)


@pytest.mark.sweep
def test_random_requests_leave_the_container_healthy(probe: Node, fuzz_node: Node, tmp_path: pathlib.Path) -> None:
    seed = environment_seed()
    requests = int(os.environ.get("IPC_FUZZ_REQUESTS") or SWEEP_REQUESTS)
    run_fuzz(probe, fuzz_node, tmp_path, seed, requests, rss_growth_limit=RSS_GROWTH_LIMIT)
