"""Finding component containers on the ROS graph and asking them for their components.

A container is a node that is not hidden and offers all three services ``<node>/_container/load_node``,
``<node>/_container/unload_node`` and ``<node>/_container/list_nodes`` with the composition_interfaces
types, exactly what ``ros2 component`` looks for.

Discovery of a freshly started participant is not instant: on a quiet localhost it usually completes in
about 0.1 s, but when the first exchange of participant announcements is missed, a peer is only seen at its
next periodic announcement, up to about 3 s later (Fast DDS announces every 3 s). Everything here therefore
polls the graph against a deadline, never waits without one, and lists containers while discovery is still
going on, so that one overall budget covers both.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from composition_interfaces.srv import ListNodes
from rclpy.executors import Executor
from rclpy.node import Node
from rclpy.task import Future

HIDDEN_NODE_PREFIX = "_"
CONTAINER_SERVICES = {
    "load_node": "composition_interfaces/srv/LoadNode",
    "unload_node": "composition_interfaces/srv/UnloadNode",
    "list_nodes": "composition_interfaces/srv/ListNodes",
}
POLL_PERIOD = 0.05


def full_node_name(name: str, namespace: str) -> str:
    """``/ns/name`` from a node's name and namespace (``/`` being the root namespace)."""
    return f"{namespace.rstrip('/')}/{name}"


def is_container(services: list[tuple[str, list[str]]], full_name: str) -> bool:
    """Whether ``services`` (a node's service names and types) make it a component container."""
    offered = dict(services)
    return all(srv_type in offered.get(f"{full_name}/_container/{srv}", ())
               for srv, srv_type in CONTAINER_SERVICES.items())


def find_containers(node: Node) -> list[str]:
    """Full names of the containers the graph shows right now, sorted."""
    containers = set()
    for name, namespace in node.get_node_names_and_namespaces():
        if name.startswith(HIDDEN_NODE_PREFIX):
            continue
        full_name = full_node_name(name, namespace)
        try:
            services = node.get_service_names_and_types_by_node(name, namespace)
        except Exception:  # noqa: BLE001 - the node left the graph between the two calls
            continue
        if is_container(services, full_name):
            containers.add(full_name)
    return sorted(containers)


@dataclass
class ContainerListing:
    """What listing one container gave: the components, or why there are none."""

    container: str
    components: list[tuple[int, str]] = field(default_factory=list)
    error: str | None = None


class _Lister:
    """The ListNodes exchange with one container, advanced step by step from the polling loop."""

    def __init__(self, node: Node, container: str) -> None:
        self.container = container
        self.client = node.create_client(ListNodes, f"{container}/_container/list_nodes")
        self.future: Future | None = None

    def step(self) -> None:
        if self.future is None and self.client.service_is_ready():
            self.future = self.client.call_async(ListNodes.Request())

    @property
    def done(self) -> bool:
        return self.future is not None and self.future.done()

    def outcome(self) -> ContainerListing:
        if self.future is None:
            return ContainerListing(self.container, error="No 'list_nodes' service found")
        if not self.future.done():
            self.future.cancel()
            return ContainerListing(self.container, error="No 'list_nodes' service response")
        response: Any = self.future.result()
        return ContainerListing(
            self.container, list(zip(response.unique_ids, response.full_node_names)))


def list_containers(node: Node, executor: Executor, *, deadline: float, discovery_until: float,
                    container: str | None = None, list_components: bool = True) -> list[ContainerListing]:
    """Discover containers and (optionally) list their components, all before ``deadline``.

    Without ``container``, the graph is watched until ``discovery_until`` and every container found is
    listed as soon as it appears. With ``container``, discovery stops as soon as that one is found; the
    result is empty if it is not found before ``deadline``. Listing failures (service not ready, no reply
    before the deadline) are reported in :attr:`ContainerListing.error`.
    """
    discovery_until = min(discovery_until, deadline) if container is None else deadline
    found: set[str] = set()
    listers: dict[str, _Lister] = {}
    try:
        discovering = True
        while True:
            if discovering:
                current = find_containers(node)
                if container is not None:
                    current = [name for name in current if name == container]
                    discovering = not current
                found.update(current)
                if list_components:
                    for name in current:
                        if name not in listers:
                            listers[name] = _Lister(node, name)
                if time.monotonic() >= discovery_until:
                    discovering = False
            for lister in listers.values():
                lister.step()
            if not discovering and all(lister.done for lister in listers.values()):
                break
            if time.monotonic() >= deadline:
                break
            executor.spin_once(timeout_sec=min(POLL_PERIOD, max(0.0, deadline - time.monotonic())))
        return [listers[name].outcome() if name in listers else ContainerListing(name)
                for name in sorted(found)]
    finally:
        for lister in listers.values():
            node.destroy_client(lister.client)
