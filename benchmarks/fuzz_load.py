#!/usr/bin/env python3
"""The fuzz scenario of tests/test_fuzz.py at benchmark scale (default 50 000 requests), with its findings.

Same container, drivers, recorder and request generator (tests/fuzz_scene.py); prints the request counts,
the most frequent refusals, requests per second, RSS before / after, the drivers' rates afterwards, the
bags and any file written outside the bag root. The result goes into the README.

    python benchmarks/fuzz_load.py [--requests 50000] [--seed N]

Isolation: a random ``ROS_DOMAIN_ID`` (unless set) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, set
before rclpy is imported; the container is stopped by its pid.
"""
from __future__ import annotations

import isolation  # noqa: F401  (first: the ROS environment before rclpy is imported)

import argparse  # noqa: E402
import os  # noqa: E402
import pathlib  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402

import rclpy  # noqa: E402

from container_process import listing  # noqa: E402
from fuzz_pipeline import LATE  # noqa: E402
from fuzz_scene import RATES, FuzzScene, environment_seed, file_listing, rss_bytes  # noqa: E402

TMP = pathlib.Path("/tmp")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=50_000)
    parser.add_argument("--seed", type=int, default=None, help="default: IPC_FUZZ_SEED or a fresh one")
    args = parser.parse_args()
    seed = environment_seed() if args.seed is None else args.seed
    rclpy.init()
    probe = rclpy.create_node("_fuzz_probe")
    fuzz_node = rclpy.create_node("_fuzz_requests")
    healthy = True
    with tempfile.TemporaryDirectory() as workdir, FuzzScene(probe, pathlib.Path(workdir)) as scene:
        cwd_before = file_listing(scene.cwd)
        tmp_before = scene.escaped(TMP)
        rss_before = rss_bytes(scene.process.pid)
        print(f"seed {seed}, {args.requests} requests; machine load {os.getloadavg()[0]:.2f}", flush=True)
        report = scene.fuzz(seed, args.requests, fuzz_node)
        print(report.summary())
        for message in report.internal_errors[:10]:
            print(f"  internal error: {message}")
        alive = scene.process.alive()
        listed = sorted(name for _uid, name in listing(scene.client)) if alive else []
        rss_after = rss_bytes(scene.process.pid) if alive else 0
        print(f"container alive: {alive}; listed afterwards: {listed}")
        print(f"RSS: {rss_before / 2**20:.1f} MiB before, {rss_after / 2**20:.1f} MiB after "
              f"(+{(rss_after - rss_before) / 2**20:.1f} MiB)")
        rates = scene.message_rates()
        print("rates afterwards: " + ", ".join(f"{topic} {rates[topic]:.1f}/s (nominal {rate:g})"
                                                for topic, (_type, rate) in RATES.items()))
        scene.finish_recorder()
        bags = scene.bags()
        print(f"bags under the bag root: {len(bags)}; baseline bag messages: {bags.get('baseline_bag')}")
        status = scene.process.stop(signal.SIGINT)
        print(f"container exit status: {status}; machine load {os.getloadavg()[0]:.2f}")
        escaped_cwd = file_listing(scene.cwd) - cwd_before
        escaped_tmp = scene.escaped(TMP) - tmp_before
        print(f"written outside the bag root: cwd {sorted(escaped_cwd)[:10]}, /tmp {sorted(escaped_tmp)[:10]}")
        unanswered = {kind: (report.counts.abandoned.get(kind, 0), report.counts.late.get(kind, 0))
                      for kind in report.counts.sent if report.counts.abandoned.get(kind) or report.counts.late.get(kind)}
        print(f"requests without a reply, or answered after {LATE:g} s (no reply, late): {unanswered or 'none'}")
        healthy = alive and status == 0 and not escaped_cwd and not escaped_tmp and not report.internal_errors \
            and not unanswered
    fuzz_node.destroy_node()
    probe.destroy_node()
    rclpy.try_shutdown()
    return 0 if healthy else 1


if __name__ == "__main__":
    sys.exit(main())
