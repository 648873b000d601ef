"""Many service calls in flight at once from one rclpy node: what makes 5000 fuzz requests take seconds.

One round trip at a time would spend most of the run waiting for DDS; here up to ``max_in_flight`` futures
are pending and the executor is spun until each completes or times out. A request that gets no reply in
time is abandoned and counted (a recorder's services keep only 10 requests queued, and a fresh client may
lose its first replies while the server has not matched it yet, see ipc_component.repeated_call).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

from rclpy.client import Client
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future


#: A reply later than this (s) is counted as late: every request must be answered within it.
LATE = 5.0


@dataclass
class _Pending:
    client: Client
    future: Future
    deadline: float
    kind: str
    on_reply: Callable[[Any], None]
    sent_at: float


@dataclass
class PipelineCounts:
    """Per request kind: sent, answered, answered later than :data:`LATE`, abandoned (no reply within the
    timeout), and the slowest reply (s)."""

    sent: dict[str, int] = field(default_factory=dict)
    answered: dict[str, int] = field(default_factory=dict)
    late: dict[str, int] = field(default_factory=dict)
    abandoned: dict[str, int] = field(default_factory=dict)
    slowest: dict[str, float] = field(default_factory=dict)

    def add(self, other: "PipelineCounts") -> None:
        """Take in the counts of another run: sums, and the slowest of both."""
        for mine, theirs in ((self.sent, other.sent), (self.answered, other.answered), (self.late, other.late),
                             (self.abandoned, other.abandoned)):
            for kind, count in theirs.items():
                mine[kind] = mine.get(kind, 0) + count
        for kind, seconds in other.slowest.items():
            self.slowest[kind] = max(self.slowest.get(kind, 0.0), seconds)


class Pipeline:
    """Bounded concurrent calls; :meth:`submit` blocks (spinning) while ``max_in_flight`` are pending."""

    def __init__(self, node: Node, max_in_flight: int = 32, timeout: float = 30.0) -> None:
        self.node = node
        self.max_in_flight = max_in_flight
        self.timeout = timeout
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(node)
        self.counts = PipelineCounts()
        self._pending: list[_Pending] = []

    def submit(self, client: Client, request: Any, kind: str, on_reply: Callable[[Any], None],
               timeout: float | None = None) -> None:
        while len(self._pending) >= self.max_in_flight:
            self.pump()
        future = client.call_async(request)
        now = time.monotonic()
        self._pending.append(_Pending(client, future, now + (timeout or self.timeout), kind, on_reply, now))
        self.counts.sent[kind] = self.counts.sent.get(kind, 0) + 1

    def pump(self) -> None:
        """Spin once, hand finished replies to their callbacks and abandon the overdue calls."""
        self.executor.spin_once(timeout_sec=0.005)
        now = time.monotonic()
        still: list[_Pending] = []
        for call in self._pending:
            if call.future.done():
                self.counts.answered[call.kind] = self.counts.answered.get(call.kind, 0) + 1
                waited = now - call.sent_at
                self.counts.slowest[call.kind] = max(waited, self.counts.slowest.get(call.kind, 0.0))
                if waited > LATE:
                    self.counts.late[call.kind] = self.counts.late.get(call.kind, 0) + 1
                call.on_reply(call.future.result())
            elif now > call.deadline:
                call.future.cancel()
                call.client.remove_pending_request(call.future)
                self.counts.abandoned[call.kind] = self.counts.abandoned.get(call.kind, 0) + 1
            else:
                still.append(call)
        self._pending = still

    def drain(self) -> None:
        while self._pending:
            self.pump()

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.executor.shutdown(timeout_sec=1.0)
