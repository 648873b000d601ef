"""A plain rclpy client of a container's three services, as ``ros2 component`` and launch_ros use them."""
from __future__ import annotations

import time
from typing import Any

from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from rclpy.node import Node

from component_container.parameter_values import parameter_msg
from ipc_testing.calls import call


class ContainerClient:
    """LoadNode / UnloadNode / ListNodes of the container ``container``, called through ``node``."""

    def __init__(self, node: Node, container: str = "/ComponentManager") -> None:
        self.node = node
        self.container = container
        self._load = node.create_client(LoadNode, f"{container}/_container/load_node")
        self._unload = node.create_client(UnloadNode, f"{container}/_container/unload_node")
        self._list = node.create_client(ListNodes, f"{container}/_container/list_nodes")

    def wait(self, timeout: float = 20.0) -> None:
        """Wait until the three services are discovered *and* replies come back.

        ``wait_for_service`` returns once this side has matched the service's endpoints; the container may not
        have matched this client's reply reader yet, and Fast DDS then drops the reply, the race launch_ros and
        ``ros2 component`` users hit too. So each service is called with a harmless request until it answers:
        ListNodes, UnloadNode of id 0 (never allocated) and a LoadNode of an empty package name (refused before
        an id is allocated).
        """
        deadline = time.monotonic() + timeout
        for client, request in ((self._list, ListNodes.Request()), (self._unload, UnloadNode.Request()),
                                (self._load, LoadNode.Request())):
            call(self.node, client, request, max(0.1, deadline - time.monotonic()), again=True)

    def load(self, plugin: str, package: str = "components", *, name: str = "", namespace: str = "",
             parameters: dict[str, Any] | None = None, extra: dict[str, Any] | None = None,
             remaps: list[str] | None = None, log_level: int = 0, timeout: float = 20.0) -> LoadNode.Response:
        request = LoadNode.Request(
            package_name=package, plugin_name=plugin, node_name=name, node_namespace=namespace,
            log_level=log_level, remap_rules=remaps or [],
            parameters=[parameter_msg(k, v) for k, v in (parameters or {}).items()],
            extra_arguments=[parameter_msg(k, v) for k, v in (extra or {}).items()])
        return call(self.node, self._load, request, timeout)

    def unload(self, unique_id: int, timeout: float = 20.0) -> UnloadNode.Response:
        return call(self.node, self._unload, UnloadNode.Request(unique_id=unique_id), timeout)

    def list(self, timeout: float = 20.0) -> ListNodes.Response:
        return call(self.node, self._list, ListNodes.Request(), timeout, again=True)

    def listing(self) -> list[tuple[int, str]]:
        response = self.list()
        return list(zip(response.unique_ids, response.full_node_names))

    def destroy(self) -> None:
        for client in (self._load, self._unload, self._list):
            self.node.destroy_client(client)
