#!/usr/bin/env python3
"""Wall-clock time of ``ipc-component list`` / ``load`` / ``unload`` against a container that already runs.

Why a script and not a test: the target (each verb within 1.5 s) depends on the machine and its load, so it
is measured and reported (docs/performance.md), never asserted.

Each command is run as a user runs it: the installed console script as a fresh process whose environment
has no ``_ROS_WHEELS_BOOTSTRAP_COMPLETE`` (so the ros_wheels_bootstrapper start-up re-exec is included, as in
a shell). The container is started first and answered once, so discovery of the command's own participant
is what is measured, not the container's start-up. Between runs, the container is put back into the same
state with a plain rclpy client (a Talker loaded before each ``unload`` run, the loaded one removed after
each ``load`` run); that is not timed. The times go to ``cli_latency.json`` in a result folder
(benchmarks/result_folder.py), whose table docs/performance.md shows.

    python benchmarks/cli_latency.py [--runs 10] [--results DIR]

Isolation: a random ``ROS_DOMAIN_ID`` (unless set) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, set
before rclpy is imported; the container is stopped by its pid.
"""
from __future__ import annotations

import isolation  # noqa: F401  (first: the ROS environment before rclpy is imported)

import argparse  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Callable, Sequence  # noqa: E402

import rclpy  # noqa: E402

from benchmarks.locations import RESULTS  # noqa: E402
from benchmarks.result_folder import run_environment, run_header, save  # noqa: E402
from ipc_testing import ContainerClient, ContainerProcess  # noqa: E402

CONTAINER = "/ComponentManager"
TALKER = "components::Talker"
TARGET = 1.5  # s per command, reported (never asserted)


def user_environment() -> dict[str, str]:
    """This environment as a shell would give it: without what the bootstrapper's re-exec of us added."""
    env = dict(os.environ)
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    env.pop("LD_LIBRARY_PATH", None)
    return env


def timed_run(command: Sequence[str], env: dict[str, str]) -> float:
    """Seconds one command took; raises if it failed (a failing command's time means nothing)."""
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=60)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({result.returncode}): {result.stderr}")
    return seconds


def measure(runs: int, command: Callable[[], list[str]], before: Callable[[], None],
            after: Callable[[], None], env: dict[str, str]) -> list[float]:
    seconds = []
    for _ in range(runs):
        before()
        seconds.append(timed_run(command(), env))
        after()
    return seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--results", default=str(RESULTS), help="the result folder goes under this directory "
                                                                 "('': none)")
    args = parser.parse_args(argv)
    report = run_header("cli_latency.py", list(argv if argv is not None else sys.argv[1:]))
    report.update(environment=run_environment(), runs=args.runs, container=CONTAINER, target_s=TARGET, commands={})
    started = time.monotonic()
    tool = shutil.which("ipc-component", path=str(Path(sys.executable).parent))
    if tool is None:
        raise SystemExit("ipc-component is not installed next to this Python")
    env = user_environment()
    rclpy.init()
    node = rclpy.create_node("_cli_latency")
    with tempfile.TemporaryDirectory() as cwd, ContainerProcess(cwd=cwd) as container:
        client = ContainerClient(node, CONTAINER)
        client.wait(timeout=30.0)
        loaded: list[int] = []

        def load_talker() -> None:
            response = client.load(TALKER)
            assert response.success, response
            loaded.append(response.unique_id)

        def unload_all() -> None:
            for unique_id in client.list().unique_ids:
                assert client.unload(unique_id).success
            loaded.clear()

        def nothing() -> None:
            pass

        cases: dict[str, tuple[Callable[[], list[str]], Callable[[], None], Callable[[], None]]] = {
            "list": (lambda: [tool, "list"], load_talker, unload_all),
            f"list {CONTAINER}": (lambda: [tool, "list", CONTAINER], load_talker, unload_all),
            "load": (lambda: [tool, "load", CONTAINER, "components", TALKER], nothing, unload_all),
            "unload": (lambda: [tool, "unload", CONTAINER, str(loaded[-1])], load_talker, unload_all),
        }
        print(f"{args.runs} runs each, container {CONTAINER} running; machine load {os.getloadavg()[0]:.2f}")
        print(f"{'command':<38} {'min':>6} {'median':>7} {'max':>6}  (s, target {TARGET:g})")
        for name, (command, before, after) in cases.items():
            seconds = measure(args.runs, command, before, after, env)
            report["commands"]["ipc-component " + name] = {"seconds": seconds}
            print(f"{'ipc-component ' + name:<38} {min(seconds):6.2f} {statistics.median(seconds):7.2f} "
                  f"{max(seconds):6.2f}", flush=True)
        print(f"machine load afterwards {os.getloadavg()[0]:.2f}")
        status = container.stop()
    node.destroy_node()
    rclpy.try_shutdown()
    report.update(loadavg_end=os.getloadavg(), elapsed_s=time.monotonic() - started, container_exit=status)
    if args.results:
        print(f"results: {save(report, 'cli_latency', Path(args.results))}")
    return 0 if status == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
