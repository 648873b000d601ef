#!/usr/bin/env python3
"""What one executor wake-up costs with N entities: rclpy's SingleThreadedExecutor against the container's.

One node holds ``--entities`` idle entities (subscriptions with their QoS event handlers, services, guard
conditions, slow timers, in equal parts) and one timer firing at ``--rate`` Hz, so that each wake-up is one
timer callback. The executor thread's CPU time (``time.thread_time`` in the callback) divided by the callbacks
is the cost of a wake-up: waiting, building or refilling the wait set, handing the callback out. Executors are
run interleaved, ``--rounds`` times each, in a fresh ROS context on a random domain.

    python benchmarks/executor_wakeup.py [--entities 0,48,102] [--seconds 2] [--rate 1000] [--rounds 2]
"""
from __future__ import annotations

import argparse
import os
import random
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import rclpy  # noqa: E402
from rclpy.executors import Executor, SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from component_container.component_executors import SupervisedSingleThreadedExecutor  # noqa: E402

EXECUTORS = {"rclpy": SingleThreadedExecutor, "supervised": SupervisedSingleThreadedExecutor}


def idle_entities(node: Node, count: int) -> None:
    """``count`` entities that never fire, a quarter of each kind (a subscription brings its event handler)."""
    for index in range(count):
        kind = index % 4
        if kind == 0:
            node.create_subscription(String, f"idle_{index}", lambda _msg: None, 1)
        elif kind == 1:
            node.create_service(Trigger, f"idle_{index}", lambda _req, resp: resp)
        elif kind == 2:
            node.create_guard_condition(lambda: None)
        else:
            node.create_timer(3600.0, lambda: None)


def microseconds_per_wakeup(make: type[Executor], entities: int, seconds: float, rate: float) -> float:
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=random.randint(1, 200))
    node = Node("wakeup_bench", context=context)
    idle_entities(node, entities)
    executor = make(context=context)
    executor.add_node(node)
    samples: list[float] = []
    node.create_timer(1.0 / rate, lambda: samples.append(time.thread_time()))
    deadline = time.monotonic() + seconds
    try:
        while time.monotonic() < deadline:
            executor.spin_once()
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
    warm = samples[len(samples) // 10:]  # the first wake-ups build the wait set and warm caches
    return (warm[-1] - warm[0]) / (len(warm) - 1) * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--entities", default="0,48,102", help="idle entity counts, comma-separated")
    parser.add_argument("--seconds", type=float, default=2.0, help="spin time per run")
    parser.add_argument("--rate", type=float, default=1000.0, help="wake-ups per second (the busy timer)")
    parser.add_argument("--rounds", type=int, default=2, help="runs per executor and count, interleaved")
    args = parser.parse_args()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    print(f"{'entities':>8}  " + "  ".join(f"{name + ' µs':>14}" for name in EXECUTORS))
    for count in (int(n) for n in args.entities.split(",")):
        results: dict[str, list[float]] = {name: [] for name in EXECUTORS}
        for _ in range(args.rounds):
            for name, make in EXECUTORS.items():
                results[name].append(microseconds_per_wakeup(make, count, args.seconds, args.rate))
        print(f"{count:>8}  " + "  ".join(f"{statistics.median(v):>14.1f}" for v in results.values()))


if __name__ == "__main__":
    main()
