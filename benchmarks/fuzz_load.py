#!/usr/bin/env python3
"""The fuzz scenario of tests/test_fuzz.py at benchmark scale (default 50 000 requests per seed), with its findings.

Same container, drivers, recorder and request generator (tests/fuzz_scene.py). The requests of a seed go out in
``--parts`` (30) equal parts; after each part the pipeline has drained and every component a request loaded is
unloaded again, and the container's RSS is read there: moments comparable to each other. Reported per seed: the
request counts, the most frequent refusals, requests per second, the RSS samples with the growth over the last
third of the requests and least-squares slopes, the drivers' rates afterwards, the bags and any file written
outside the bag root.

A seed passes when every LoadNode / UnloadNode request was answered within 5 s, no request hit an internal
error, the container is alive and exits 0, the drivers publish at 90 % of their rates or more afterwards, nothing
was written outside the bag root, and the RSS grew by less than 10 MiB over the last third of the requests (the
first two thirds warm up what a long-running container keeps). Exit status 1 when a seed failed.

    python benchmarks/fuzz_load.py [--requests 50000] [--seed N [--seed M ...]] [--parts 30] [--results DIR]

The results go to a folder of their own under benchmarks/results/ (``fuzz_load.json`` and its table).
Isolation: a random ``ROS_DOMAIN_ID`` (unless set) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, set
before rclpy is imported; the container is stopped by its pid.
"""
from __future__ import annotations

import isolation  # noqa: F401  (first: the ROS environment before rclpy is imported)

import argparse  # noqa: E402
import os  # noqa: E402
import pathlib  # noqa: E402
import random  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import rclpy  # noqa: E402
from rclpy.node import Node  # noqa: E402

from benchmarks.endurance.resources import least_squares_slope  # noqa: E402
from benchmarks.result_folder import RESULTS, run_header, save  # noqa: E402
from container_process import listing  # noqa: E402
from fuzz_pipeline import LATE  # noqa: E402
from fuzz_scene import RATES, FuzzReport, FuzzScene, environment_seed, file_listing, rss_bytes  # noqa: E402

TMP = pathlib.Path("/tmp")
MIB = 2**20
RSS_GROWTH_LIMIT_MIB = 10.0  # over the last third of the requests
RATE_SHARE = 0.9             # the drivers' rates afterwards, at least this share of nominal


def sampled_fuzz(scene: FuzzScene, seed: int, requests: int, parts: int, fuzz_node: Node
                 ) -> tuple[FuzzReport, list[tuple[int, float]]]:
    """``requests`` requests of ``seed`` in ``parts`` parts (each part's generator seeded from ``seed``); the
    container's RSS (MiB) before the first part and after each, with the requests sent so far."""
    seeds = random.Random(seed)
    report = FuzzReport(seed, 0)
    samples = [(0, rss_bytes(scene.process.pid) / MIB)]
    for part in range(parts):
        count = requests * (part + 1) // parts - report.requests
        report.add(scene.fuzz(seeds.randrange(2**32), count, fuzz_node))
        samples.append((report.requests, rss_bytes(scene.process.pid) / MIB))
    report.seed = seed
    return report, samples


def rss_report(samples: list[tuple[int, float]]) -> dict[str, Any]:
    """Growth over the last third of the requests, slopes (MiB per 10 000 requests) over it and the whole run."""
    total = samples[-1][0]
    last_third = [(n, rss) for n, rss in samples if n >= total - total // 3]
    per_10k = lambda points: 1e4 * (least_squares_slope(points) or 0.0)  # noqa: E731
    growth = last_third[-1][1] - last_third[0][1]
    return {"samples": samples, "start_mib": samples[0][1], "end_mib": samples[-1][1],
            "last_third_start_mib": last_third[0][1], "growth_last_third_mib": growth,
            "slope_last_third_mib_per_10k": per_10k(last_third), "slope_mib_per_10k": per_10k(samples),
            "ok": growth < RSS_GROWTH_LIMIT_MIB}


def run_seed(seed: int, args: argparse.Namespace, probe: Node, fuzz_node: Node) -> dict[str, Any]:
    """One seed in a fresh scene: the requests, then every check (module docstring)."""
    with tempfile.TemporaryDirectory() as workdir, FuzzScene(probe, pathlib.Path(workdir)) as scene:
        cwd_before, tmp_before = file_listing(scene.cwd), scene.escaped(TMP)
        load_before = os.getloadavg()[0]
        print(f"seed {seed}, {args.requests} requests in {args.parts} parts; machine load {load_before:.2f}",
              flush=True)
        report, samples = sampled_fuzz(scene, seed, args.requests, args.parts, fuzz_node)
        print(report.summary())
        for message in report.internal_errors[:10]:
            print(f"  internal error: {message}")
        alive = scene.process.alive()
        listed = sorted(name for _uid, name in listing(scene.client)) if alive else []
        rates = scene.message_rates() if alive else {}
        scene.finish_recorder()
        bags = scene.bags()
        status = scene.process.stop(signal.SIGINT)
        escaped = sorted(file_listing(scene.cwd) - cwd_before) + sorted(scene.escaped(TMP) - tmp_before)
    unanswered = {kind: (report.counts.abandoned.get(kind, 0), report.counts.late.get(kind, 0))
                  for kind in ("load", "unload") if report.counts.abandoned.get(kind) or report.counts.late.get(kind)}
    slow = {topic: rates.get(topic, 0.0) for topic, (_type, rate) in RATES.items()
            if rates.get(topic, 0.0) < RATE_SHARE * rate}
    rss = rss_report(samples)
    checks = {"answered within 5 s": not unanswered, "no internal error": not report.internal_errors,
              "container alive, exit status 0": alive and status == 0, "drivers at rate": not slow,
              "nothing written outside the bag root": not escaped,
              f"RSS growth over the last third < {RSS_GROWTH_LIMIT_MIB:g} MiB": rss["ok"]}
    return {"seed": seed, "requests": report.requests, "seconds": report.seconds, "sent": report.counts.sent,
            "late": report.counts.late, "abandoned": report.counts.abandoned, "slowest_s": report.counts.slowest,
            "loaded": report.loaded, "internal_errors": report.internal_errors[:10],
            "load_errors": dict(report.load_errors.most_common(12)), "listed_afterwards": listed,
            "rates": rates, "bags": len(bags), "baseline_bag_messages": bags.get("baseline_bag"),
            "exit_status": status, "escaped": escaped[:10], "unanswered": unanswered, "rss": rss,
            "loadavg": [load_before, os.getloadavg()[0]], "checks": checks, "healthy": all(checks.values())}


def print_seed(result: dict[str, Any]) -> None:
    rss = result["rss"]
    print(f"container listed afterwards: {result['listed_afterwards']}; exit status {result['exit_status']}")
    print(f"RSS: {rss['start_mib']:.1f} MiB at the start, {rss['last_third_start_mib']:.1f} at 2/3 of the requests, "
          f"{rss['end_mib']:.1f} at the end: +{rss['growth_last_third_mib']:.1f} MiB over the last third; slope "
          f"{rss['slope_last_third_mib_per_10k']:+.2f} MiB per 10 000 requests over it, "
          f"{rss['slope_mib_per_10k']:+.2f} over the whole run")
    print("rates afterwards: " + ", ".join(f"{topic} {result['rates'].get(topic, 0.0):.1f}/s (nominal {rate:g})"
                                            for topic, (_type, rate) in RATES.items()))
    print(f"bags under the bag root: {result['bags']}; baseline bag messages: {result['baseline_bag_messages']}")
    print(f"written outside the bag root: {result['escaped'] or 'nothing'}; requests without a reply, or "
          f"answered after {LATE:g} s (no reply, late): {result['unanswered'] or 'none'}")
    for check, ok in result["checks"].items():
        print(f"  {'PASS' if ok else 'FAIL'}  {check}")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument("--requests", type=int, default=50_000, help="requests per seed")
    parser.add_argument("--seed", type=int, action="append",
                        help="repeatable; default: IPC_FUZZ_SEED or a fresh one")
    parser.add_argument("--parts", type=int, default=30, help="parts of a seed's requests, an RSS sample after each")
    parser.add_argument("--results", default=str(RESULTS),
                        help="the result folder (fuzz_load.json and its table) goes under this directory ('': none)")
    args = parser.parse_args(argv)
    if args.parts < 3 or args.requests < args.parts:
        parser.error("--parts must be at least 3, and --requests at least --parts")
    report: dict[str, Any] = {**run_header("fuzz_load.py", argv), "seeds": []}
    started = time.monotonic()
    rclpy.init()
    probe, fuzz_node = rclpy.create_node("_fuzz_probe"), rclpy.create_node("_fuzz_requests")
    try:
        for seed in args.seed or [environment_seed()]:
            report["seeds"].append(run_seed(seed, args, probe, fuzz_node))
            print_seed(report["seeds"][-1])
    finally:
        fuzz_node.destroy_node()
        probe.destroy_node()
        rclpy.try_shutdown()
    report["elapsed_s"] = time.monotonic() - started
    if args.results:
        print(f"results: {save(report, 'fuzz_load', pathlib.Path(args.results))}", file=sys.stderr)
    return 0 if all(result["healthy"] for result in report["seeds"]) else 1


if __name__ == "__main__":
    sys.exit(main())
