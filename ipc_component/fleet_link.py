"""Talking to many containers at once: their clients, made ready together, calls in parallel, clock offsets.

A fleet command (``ipc-component record ...``) addresses every container of the domain, on every computer.
Calls go out to all of them at once and are waited for against one deadline, so one container that does not
answer costs the budget once and is named, while the others go ahead.

Clock offsets are measured the NTP way (RFC 5905, on-wire protocol): the command reads its clock (t0), asks the
container's ``~/_container/clock`` service for its clock (t1 = t2: read while answering), and reads its clock again
when the reply arrives (t3). The offset is ``t1 - (t0 + t3) / 2``, and it is off by at most half the round trip,
``(t3 - t0) / 2``; of several exchanges the one with the shortest round trip counts.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from rcl_interfaces.srv import SetParameters
from rclpy.client import Client
from rclpy.task import Future
from std_srvs.srv import Trigger

from ipc_component.repeated_call import RepeatedCall

#: Exchanges per clock-offset measurement; the fastest counts.
CLOCK_EXCHANGES = 8
SPIN_STEP = 0.01  # s


@dataclass(frozen=True)
class ClockOffset:
    """A container's clock minus this computer's, with its error bound (both ns)."""

    offset_ns: int
    uncertainty_ns: int


@dataclass
class ContainerLink:
    """One container's clients. Created in this order, so that once the clock service (created last) has answered,
    the container has matched the reply readers of all of them (endpoints are announced in creation order)."""

    name: str
    load: Client
    unload: Client
    list_nodes: Client
    clock: Client
    host: str = ""
    bag_root: str = ""
    offset: ClockOffset | None = None
    error: str = ""
    extra: dict[str, Client] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.error


class Fleet:
    """The containers a command addresses, through one node and its executor."""

    def __init__(self, node: Any, executor: Any, containers: Sequence[str]) -> None:
        self.node, self.executor = node, executor
        self.links = [ContainerLink(name, node.create_client(LoadNode, f"{name}/_container/load_node"),
                                    node.create_client(UnloadNode, f"{name}/_container/unload_node"),
                                    node.create_client(ListNodes, f"{name}/_container/list_nodes"),
                                    node.create_client(Trigger, f"{name}/_container/clock"))
                      for name in containers]

    @property
    def answering(self) -> list[ContainerLink]:
        return [link for link in self.links if link.ok]

    def spin_until(self, done: Any, deadline: float) -> bool:
        """Spin until ``done()`` or ``deadline``; whether ``done()`` came true."""
        while not done():
            if time.monotonic() >= deadline:
                return False
            self.executor.spin_once(timeout_sec=SPIN_STEP)
        return True

    def connect(self, deadline: float) -> None:
        """Ask every container for its clock until each answered (which makes all its clients ready); a
        container that does not answer by ``deadline`` gets an error and is left out of what follows."""
        replies = self.repeat_all({link.name: (link.clock, Trigger.Request()) for link in self.answering}, deadline)
        for link in self.answering:
            reply = replies.get(link.name)
            if reply is None:
                link.error = "did not answer"
                continue
            facts = json.loads(reply.message)
            link.host, link.bag_root = facts["host"], facts["bag_root"]
            servers = len(self.node.get_subscriptions_info_by_topic(f"rq{link.name}/_container/clockRequest",
                                                                     no_mangle=True))
            if servers > 1:
                link.error = (f"{servers} containers have this name: a request would reach all of them; give each "
                              "container a name of its own (-r __ns:=/<computer>)")

    def measure_offsets(self, deadline: float) -> None:
        """The clock offset of every answering container (one after the other: a round trip is short)."""
        for link in self.answering:
            best: tuple[int, int] | None = None
            for _ in range(CLOCK_EXCHANGES):
                sample = self._exchange(link, deadline)
                if sample is not None and (best is None or sample[1] < best[1]):
                    best = sample
            if best is None:
                link.error = "did not answer the clock exchange"
            else:
                link.offset = ClockOffset(*best)

    def _exchange(self, link: ContainerLink, deadline: float) -> tuple[int, int] | None:
        """One exchange: (offset, uncertainty) in ns, or None without a reply by ``deadline``."""
        arrived: list[int] = []
        t0 = time.time_ns()
        future = link.clock.call_async(Trigger.Request())
        future.add_done_callback(lambda _future: arrived.append(time.time_ns()))
        if not self.spin_until(lambda: bool(arrived), deadline):
            _forget(link.clock, future)
            return None
        t1 = json.loads(future.result().message)["time_ns"]
        t3 = arrived[0]
        return t1 - (t0 + t3) // 2, (t3 - t0) // 2

    def call_all(self, calls: dict[str, tuple[Client, Any]], deadline: float) -> dict[str, Any]:
        """Send one request per container (name -> (client, request)) at once; the replies by ``deadline``
        (a name without a reply is missing from the result)."""
        futures: dict[str, Future] = {name: client.call_async(request) for name, (client, request) in calls.items()}
        self.spin_until(lambda: all(future.done() for future in futures.values()), deadline)
        replies = {}
        for name, future in futures.items():
            if future.done() and future.exception() is None:
                replies[name] = future.result()
            else:
                _forget(calls[name][0], future)
        return replies

    def repeat_all(self, calls: dict[str, tuple[Client, Any]], deadline: float) -> dict[str, Any]:
        """Like :meth:`call_all` for idempotent requests: each is sent again until answered (a client the
        server has not matched yet loses its first replies)."""
        repeated = {name: RepeatedCall(client, lambda request=request: request)
                    for name, (client, request) in calls.items()}

        def all_answered() -> bool:
            now = time.monotonic()
            for call in repeated.values():
                call.step(now)
            return all(call.reply is not None for call in repeated.values())

        self.spin_until(all_answered, deadline)
        replies = {name: call.reply for name, call in repeated.items() if call.reply is not None}
        for call in repeated.values():
            call.close()
        return replies

    def component_client(self, link: ContainerLink, srv_type: Any, service: str) -> Client:
        """A client of a service of a component in ``link``'s container, created once."""
        if service not in link.extra:
            link.extra[service] = self.node.create_client(srv_type, service)
        return link.extra[service]

    def parameter_client(self, link: ContainerLink, node_name: str) -> Client:
        return self.component_client(link, SetParameters, f"{node_name}/set_parameters")


def _forget(client: Client, future: Future) -> None:
    if not future.done():
        future.cancel()
        client.remove_pending_request(future)
