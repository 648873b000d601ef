"""``/diagnostics``: what rqt_robot_monitor and Foxglove's diagnostics panel show about the container.

Once a second (from its own thread, so a slow unload on the manager's thread does not stall it) the container
publishes a ``diagnostic_msgs/DiagnosticArray``: one status for the container (its executor threads and the
supervisor), one per loaded component (running, plus whatever the component's ``health()`` reports, e.g. a
recorder's bag, MB/s, counts and free disk), and one error status per recently failed component.
"""
from __future__ import annotations

import threading
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from component_container.health import ERROR, OK, Health

DIAGNOSTICS_TOPIC = "/diagnostics"
PERIOD = 1.0


def status(name: str, health: Health, hardware_id: str = "") -> DiagnosticStatus:
    return DiagnosticStatus(level=bytes([health.level]), name=name, message=health.message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=str(v)) for k, v in health.values.items()])


class DiagnosticsPublisher:
    """Publishes ``collect()`` on /diagnostics every ``PERIOD`` seconds until stopped."""

    def __init__(self, node: Node, collect: Callable[[], list[DiagnosticStatus]]) -> None:
        self._node = node
        self._collect = collect
        self._publisher = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="diagnostics", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(PERIOD):
            try:
                array = DiagnosticArray(status=self._collect())
                array.header.stamp = self._node.get_clock().now().to_msg()
                self._publisher.publish(array)
            except Exception as exc:  # noqa: BLE001 - reporting must never take the container down
                if not self._node.context.ok():
                    return
                self._node.get_logger().warning(f"Publishing diagnostics failed: {exc}",
                                                throttle_duration_sec=10.0)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2 * PERIOD)


def component_health(node: Any) -> Health:
    """A component's health: its own report if it has one (a report that fails is an error itself)."""
    report = getattr(node, "health", None)
    if report is None:
        return Health()
    try:
        return report() or Health()
    except Exception as exc:  # noqa: BLE001 - a broken health() is reported, not propagated
        return Health(ERROR, f"health() raised {type(exc).__name__}: {exc}")


def threads_health(threads: dict[str, threading.Thread]) -> Health:
    dead = sorted(name for name, thread in threads.items() if not thread.is_alive())
    values = {name: ("alive" if thread.is_alive() else "dead") for name, thread in threads.items()}
    if dead:
        return Health(ERROR, f"thread(s) {', '.join(dead)} died", values)
    return Health(OK, "running", values)
