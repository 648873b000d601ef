"""Finding component containers on the ROS graph and asking them for their components.

A container is a node that is not hidden and offers all three services ``<node>/_container/load_node``,
``<node>/_container/unload_node`` and ``<node>/_container/list_nodes`` with the composition_interfaces
types, exactly what ``ros2 component`` looks for.

Containers are recognised from service names and types alone (endpoint discovery), not from node names: a
peer's node names arrive later (its ``ros_discovery_info`` sample, ~80 ms after its endpoints), and a
container's full name is the prefix of its services anyway.

Discovery of a freshly started participant is not instant: on a quiet localhost it usually completes in
about 0.1 s, but Fast DDS regularly loses the first exchange (the peer's answering announcement arrives
before the new participant listens), and a peer is then only seen at its next periodic announcement: up to
3 s later by default, at most 0.25 s later for this project's containers (component_container.
discovery_profile). Everything here therefore polls the graph against a deadline, never waits without one,
and lists containers while discovery is still going on, so that one overall budget covers both.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Collection

from composition_interfaces.srv import ListNodes
from rclpy.executors import Executor
from rclpy.node import Node

from ipc_component.repeated_call import RepeatedCall

HIDDEN_NODE_PREFIX = "_"
CONTAINER_SERVICES = {
    "load_node": "composition_interfaces/srv/LoadNode",
    "unload_node": "composition_interfaces/srv/UnloadNode",
    "list_nodes": "composition_interfaces/srv/ListNodes",
}
CONTAINER_INFIX = "/_container/"
POLL_PERIOD = 0.02


def find_containers(node: Node) -> list[str]:
    """Full names of the containers the graph shows right now, sorted."""
    offered: dict[str, dict[str, list[str]]] = {}
    for name, types in node.get_service_names_and_types():
        container, separator, service = name.rpartition(CONTAINER_INFIX)
        if separator and container and service in CONTAINER_SERVICES:
            offered.setdefault(container, {})[service] = types
    return sorted(container for container, services in offered.items()
                  if not container.rsplit("/", 1)[1].startswith(HIDDEN_NODE_PREFIX)
                  and all(srv_type in services.get(srv, ()) and _served(node, f"{container}{CONTAINER_INFIX}{srv}")
                          for srv, srv_type in CONTAINER_SERVICES.items()))


def _served(node: Node, service: str) -> bool:
    """Whether someone serves ``service``: has a reader on its request topic (``rq<service>Request``).

    The graph's service names include clients too, so without this check a command's own clients (or
    another ``ipc-component load /nowhere`` running at the same time) would make a container appear.
    """
    return bool(node.get_subscriptions_info_by_topic(f"rq{service}Request", no_mangle=True))


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
        self.call = RepeatedCall(node.create_client(ListNodes, f"{container}/_container/list_nodes"),
                                 ListNodes.Request)

    @property
    def done(self) -> bool:
        return self.call.reply is not None

    def outcome(self) -> ContainerListing:
        response: Any = self.call.reply
        if response is not None:
            return ContainerListing(self.container, list(zip(response.unique_ids, response.full_node_names)))
        if not self.call.sent:
            return ContainerListing(self.container, error="No 'list_nodes' service found")
        return ContainerListing(self.container, error="No 'list_nodes' service response")


def list_containers(node: Node, executor: Executor, *, deadline: float, discovery_until: float,
                    container: str | None = None, list_components: bool = True,
                    awaited: Collection[str] = ()) -> list[ContainerListing]:
    """Discover containers and (optionally) list their components, all before ``deadline``.

    Without ``container``, the graph is watched until ``discovery_until`` and every container found is
    listed as soon as it appears; containers named in ``awaited`` (the ones a user named exactly) are waited for
    past ``discovery_until``, until ``deadline``, as ``load`` waits for its one. With ``container``, discovery
    stops as soon as that one is found; the result is empty if it is not found before ``deadline``. Listing
    failures (service not ready, no reply before the deadline) are reported in :attr:`ContainerListing.error`.
    """
    discovery_until = min(discovery_until, deadline) if container is None else deadline
    found: set[str] = set()
    listers: dict[str, _Lister] = {}
    if container is not None and list_components:
        # Created now, the client is announced in the first discovery exchange with the container.
        listers[container] = _Lister(node, container)
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
                if time.monotonic() >= discovery_until and found.issuperset(awaited):
                    discovering = False
            now = time.monotonic()
            for lister in listers.values():
                lister.call.step(now)
            if not discovering and all(lister.done for lister in listers.values()):
                break
            if time.monotonic() >= deadline:
                break
            executor.spin_once(timeout_sec=min(POLL_PERIOD, max(0.0, deadline - time.monotonic())))
        return [listers[name].outcome() if name in listers else ContainerListing(name)
                for name in sorted(found)]
    finally:
        for lister in listers.values():
            lister.call.close()
            node.destroy_client(lister.call.client)
