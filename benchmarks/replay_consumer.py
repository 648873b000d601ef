"""The replay benchmark's consumer: counts what arrives per topic, nothing more.

One class for both modes of benchmarks/replay_bench.py. Loaded into a container as a module plugin
(``benchmarks.replay_consumer:CountingConsumer``, with ``use_intra_process_comms``) it gets the player's
message objects in-process; run as a plain process (``python -m benchmarks.replay_consumer TOPIC=TYPE ...``,
cwd the repository) its subscriptions receive over DDS and deserialize every message, as a Python pipeline's
would. Unlike tests/container_test_plugins.py:PlaybackProbe it does no per-message work beyond a count and a
clock read, so the benchmark measures delivery, not the probe.

Subscriptions are reliable keep_all. ``~/report`` (std_srvs/Trigger) answers JSON: per topic ``received``,
``dropped`` (in-process queue refusals: the container bounds keep_all queues), ``lost`` (DDS message-lost
events), ``publishers`` (matched publisher count); and ``first_ns`` / ``last_ns``, the CLOCK_MONOTONIC
times of the first and last message (comparable across processes). ``~/reset`` zeroes everything.
"""
from __future__ import annotations

import functools
import importlib
import json
import sys
import threading
import time
from typing import Any

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from component_container.component_node import ComponentNode

RELIABLE_KEEP_ALL = QoSProfile(depth=1, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)


def message_class(type_name: str) -> Any:
    package, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


class CountingConsumer(ComponentNode):
    """Subscribes to ``topics`` (parallel list ``types``) and counts (see module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("replay_consumer", **kwargs)
        topics = self.declare_parameter("topics", [""]).value
        types = self.declare_parameter("types", [""]).value
        if len(topics) != len(types) or not all(topics):
            raise ValueError("parameters 'topics' and 'types' must be non-empty lists of the same length")
        self._lock = threading.Lock()
        self._topic_subscriptions: dict[str, Any] = {}
        for topic, type_name in zip(topics, types):
            events = SubscriptionEventCallbacks(message_lost=functools.partial(self._on_lost, topic))
            self._topic_subscriptions[topic] = self.create_subscription(
                message_class(type_name), topic, functools.partial(self._on_message, topic), RELIABLE_KEEP_ALL,
                event_callbacks=events)
        self._reset()
        self._consumer_services = [self.create_service(Trigger, "~/report", self._on_report),
                          self.create_service(Trigger, "~/reset", self._on_reset)]

    def _reset(self) -> None:
        with self._lock:
            self._received = dict.fromkeys(self._topic_subscriptions, 0)
            self._lost = dict.fromkeys(self._topic_subscriptions, 0)
            self._dropped_before = {t: self._dropped(s) for t, s in self._topic_subscriptions.items()}
            self._first_ns = 0
            self._last_ns = 0

    @staticmethod
    def _dropped(subscription: Any) -> int:
        return getattr(subscription, "dropped_count", 0)  # in-process subscriptions only

    def _on_message(self, topic: str, _msg: Any) -> None:
        now = time.monotonic_ns()
        with self._lock:
            self._received[topic] += 1
            self._first_ns = self._first_ns or now
            self._last_ns = now

    def _on_lost(self, topic: str, info: Any) -> None:
        with self._lock:
            self._lost[topic] += info.total_count_change

    def report(self) -> dict[str, Any]:
        with self._lock:
            topics = {t: {"received": self._received[t], "lost": self._lost[t],
                          "dropped": self._dropped(s) - self._dropped_before[t],
                          "publishers": s.get_publisher_count()}
                      for t, s in self._topic_subscriptions.items()}
            return {"topics": topics, "first_ns": self._first_ns, "last_ns": self._last_ns}

    def _on_report(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = True, json.dumps(self.report())
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._reset()
        response.success = True
        return response


def main(argv: list[str]) -> int:
    """``TOPIC=TYPE ...``: a plain rclpy process (no container) running one consumer until SIGINT."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.parameter import Parameter

    pairs = [arg.split("=", 1) for arg in argv]
    if not pairs or any(len(pair) != 2 for pair in pairs):
        print("usage: python -m benchmarks.replay_consumer TOPIC=TYPE ...", file=sys.stderr)
        return 2
    rclpy.init()
    node = CountingConsumer(parameter_overrides=[Parameter("topics", value=[t for t, _ in pairs]),
                                                 Parameter("types", value=[t for _, t in pairs])])
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
