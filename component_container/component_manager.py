"""The container node: LoadNode / UnloadNode / ListNodes, as rclcpp_components' ComponentManager offers them.

This module is the load path: a request is validated (component_options), its plugin resolved
(plugin_registry), the component constructed with its own node options, given to the executor model
(component_executors) and recorded under a unique id. Unloading reverses it.
"""
from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from typing import Any

from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.logging import LoggingSeverity
from rclpy.node import Node
from rclpy.qos import QoSProfile

from component_container.component_executors import ComponentExecutor, make_component_executor
from component_container.component_node import ComponentNode
from component_container.component_options import LoadRequestError, options_from_request
from component_container.intra_process import IntraProcessManager
from component_container.plugin_registry import PluginError, PluginRegistry

# rclcpp_components gives load and unload a deep queue so that bursts of launch requests are not lost.
LOAD_UNLOAD_QOS = QoSProfile(depth=200)


@dataclass
class LoadedComponent:
    """A component the container owns."""

    unique_id: int
    node: Node
    package_name: str
    plugin_name: str
    logger_level_set: bool = False


class ComponentManager(Node):
    """The container node: owns the components, their executor model and the intra-process manager."""

    def __init__(self, executor_kind: str = "single", *, use_intra_process_comms: bool = False,
                 allow_module_plugins: bool = False, node_name: str = "ComponentManager",
                 **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._registry = PluginRegistry(allow_module_plugins)
        self._default_intra_process = use_intra_process_comms
        self.intra_process_manager = IntraProcessManager()
        thread_num = self.declare_parameter(
            "thread_num", os.cpu_count() or 1,
            ParameterDescriptor(read_only=True, description="threads of the multi-threaded executor")).value
        if not 1 <= thread_num <= (os.cpu_count() or 1) * 64:
            raise ValueError(f"thread_num must be a positive number of threads, got {thread_num}")
        self._executor: ComponentExecutor = make_component_executor(executor_kind, self.context, thread_num)
        self._components: dict[int, LoadedComponent] = {}
        self._last_id = 0
        self._lock = threading.Lock()
        group = MutuallyExclusiveCallbackGroup()
        self.create_service(LoadNode, "~/_container/load_node", self._on_load_node,
                            qos_profile=LOAD_UNLOAD_QOS, callback_group=group)
        self.create_service(UnloadNode, "~/_container/unload_node", self._on_unload_node,
                            qos_profile=LOAD_UNLOAD_QOS, callback_group=group)
        self.create_service(ListNodes, "~/_container/list_nodes", self._on_list_nodes, callback_group=group)

    # --- service callbacks -------------------------------------------------------------------------------
    def _on_load_node(self, request: LoadNode.Request, response: LoadNode.Response) -> LoadNode.Response:
        try:
            loaded = self.load(request)
        except (LoadRequestError, PluginError, ComponentConstructionError) as exc:
            self.get_logger().error(f"Failed to load component {request.plugin_name}: {exc}")
            response.success, response.error_message = False, str(exc)
            response.full_node_name, response.unique_id = "", 0
            return response
        response.success = True
        response.full_node_name = loaded.node.get_fully_qualified_name()
        response.unique_id = loaded.unique_id
        return response

    def _on_unload_node(self, request: UnloadNode.Request,
                        response: UnloadNode.Response) -> UnloadNode.Response:
        if self.unload(request.unique_id):
            response.success = True
        else:
            response.success = False
            response.error_message = f"No node found with unique_id: {request.unique_id}"
            self.get_logger().error(response.error_message)
        return response

    def _on_list_nodes(self, request: ListNodes.Request, response: ListNodes.Response) -> ListNodes.Response:
        for component in self.components():
            response.unique_ids.append(component.unique_id)
            response.full_node_names.append(component.node.get_fully_qualified_name())
        return response

    # --- the load path -----------------------------------------------------------------------------------
    def load(self, request: LoadNode.Request) -> LoadedComponent:
        """Construct the requested component and start executing it; raises with the caller's message."""
        node_class = self._registry.resolve(request.package_name, request.plugin_name)
        options = options_from_request(request, self._default_intra_process)
        kwargs = dict(options.node_kwargs, context=self.context)
        if issubclass(node_class, ComponentNode):
            kwargs["intra_process_manager"] = (
                self.intra_process_manager if options.use_intra_process_comms else None)
        elif options.use_intra_process_comms:
            self.get_logger().warning(
                f"{request.plugin_name} is not a ComponentNode: it communicates over DDS only")
        with self._lock:
            self._last_id += 1
            unique_id = self._last_id
        self.get_logger().info(f"Loading {request.package_name} {request.plugin_name} as id {unique_id}")
        # __new__ then __init__ (what node_class(**kwargs) does) so that a constructor that raises after the
        # rcl node exists can be cleaned up: rclcpp destroys the half-built node, here it would linger in the
        # graph (publishers, parameter services) until the garbage collector happened to break its cycles.
        node = node_class.__new__(node_class)
        try:
            node.__init__(**kwargs)
        except Exception as exc:  # a component's constructor may raise anything; report it, stay up
            _destroy_partially_constructed(node)
            raise ComponentConstructionError(f"Component constructor threw an exception: {exc}") from exc
        if options.log_level is not None:
            node.get_logger().set_level(options.log_level)
        loaded = LoadedComponent(unique_id, node, request.package_name, request.plugin_name,
                                 options.log_level is not None)
        with self._lock:
            self._components[unique_id] = loaded
        self._executor.add(node)
        return loaded

    def unload(self, unique_id: int) -> bool:
        """Stop and destroy one component; False if no component has that id."""
        with self._lock:
            loaded = self._components.pop(unique_id, None)
        if loaded is None:
            return False
        self.get_logger().info(f"Unloading {loaded.node.get_fully_qualified_name()} (id {unique_id})")
        self._executor.remove(loaded.node)
        if loaded.logger_level_set:  # logger levels outlive nodes: the next node of that name starts clean
            loaded.node.get_logger().set_level(LoggingSeverity.UNSET)
        try:
            loaded.node.destroy_node()
        except Exception as exc:  # a failing destructor must not take the container down
            self.get_logger().error(f"Destroying {loaded.plugin_name} (id {unique_id}) failed: {exc}")
        return True

    def components(self) -> list[LoadedComponent]:
        """The loaded components in ascending id order."""
        with self._lock:
            return [self._components[uid] for uid in sorted(self._components)]

    def shutdown(self) -> None:
        """Destroy every component, newest first (so recorders finalize), then stop the executors."""
        for component in reversed(self.components()):
            self.unload(component.unique_id)
        self._executor.shutdown()


class ComponentConstructionError(Exception):
    """The component's constructor raised."""


def _destroy_partially_constructed(node: Node) -> None:
    """Destroy what a failed component constructor created; a node that never got an rcl handle is ignored."""
    try:
        node.destroy_node()
    except Exception:  # noqa: BLE001 - __init__ failed before the node existed, or half-way through it
        pass
