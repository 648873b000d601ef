"""The container node: LoadNode / UnloadNode / ListNodes, as rclcpp_components' ComponentManager offers them.

This module is the load path: a request is validated (component_options), its plugin resolved
(plugin_registry), the component constructed with its own node options, given to the executor model
(component_executors) and recorded under a unique id. Unloading reverses it.
"""
from __future__ import annotations

import functools
import json
import os
import shutil
import socket
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from diagnostic_msgs.msg import DiagnosticStatus
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.exceptions import InvalidHandle
from rclpy.logging import LoggingSeverity
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from std_srvs.srv import Trigger

from component_container.callback_supervision import COMPONENT_ERRORS
from component_container.component_executors import ComponentExecutor, make_component_executor
from component_container.component_node import ComponentNode
from component_container.component_options import LoadRequestError, options_from_request
from component_container.diagnostics import DiagnosticsPublisher, component_health, status, threads_health
from component_container.health import ERROR, FREE_DISK_MB, Health
from component_container.intra_process import IntraProcessManager
from component_container.plugin_registry import PluginError, PluginRegistry
from component_container.publish_counts import UPTIME, publication_values
from component_container.supervisor import ComponentFailure, ExitRequest, Supervisor
from component_container.undeclared_parameters import undeclared_parameters, warning_text

TYPE_DESCRIPTION_SERVICE_PARAMETER = "start_type_description_service"
# rclcpp_components gives load and unload a deep queue so that bursts of launch requests are not lost.
LOAD_UNLOAD_QOS = QoSProfile(depth=200)
#: The container's clock service (std_srvs/Trigger), see ComponentManager._on_clock.
CLOCK_SERVICE = "~/_container/clock"


@dataclass(eq=False)
class LoadedComponent:
    """A component the container owns."""

    unique_id: int
    node: Node
    package_name: str
    plugin_name: str
    full_name: str  # taken at load: a component that destroyed its own node can no longer say it
    logger_level_set: bool = False
    warning: str = ""  # what the loader should know although the load succeeded (undeclared parameters)
    owner: int = 0  # the component that loaded this one (ComponentNode.load_owned_component); 0: a request


@dataclass
class UnloadResult:
    """What unloading did: ``found`` is False for an unknown id; ``error`` says what went wrong otherwise."""

    found: bool
    error: str = ""


class ComponentManager(Node):
    """The container node: owns the components, their executor model and the intra-process manager.

    Supervision (see component_container.supervisor): component callbacks that raise are reported to
    :meth:`_component_raised`, which takes the component out of ListNodes at once and hands it to the
    error policy; dying executor threads end the container. Unloading is bounded by ``shutdown_timeout``.

    Limits on what a request may do (the load service answers anyone on the ROS domain): ``allow_plugins``
    (fnmatch patterns over plugin names; empty: every registered plugin) and ``bag_root`` (a resolved
    directory every path parameter of a component must stay in; None: no limit), see docs/security.md.
    """

    def __init__(self, executor_kind: str = "single", *, use_intra_process_comms: bool = False,
                 allow_module_plugins: bool = False, allow_plugins: Sequence[str] = (),
                 bag_root: Path | None = None, node_name: str = "ComponentManager",
                 on_component_error: str = "unload", shutdown_timeout: float = 10.0,
                 exit_request: ExitRequest | None = None, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._started_ns = time.monotonic_ns()
        self._registry = PluginRegistry(allow_module_plugins, allow_plugins)
        self._default_intra_process = use_intra_process_comms
        self.shutdown_timeout = shutdown_timeout
        self.bag_root = bag_root
        self.exit_request = exit_request or ExitRequest()
        self.supervisor = Supervisor(on_component_error, self.get_logger(), self._unload_failed,
                                     self.exit_request)
        try:
            thread_num = self.declare_parameter(
                "thread_num", os.cpu_count() or 1,
                ParameterDescriptor(read_only=True, description="threads of the multi-threaded executor")).value
            if not 1 <= thread_num <= (os.cpu_count() or 1) * 64:
                raise ValueError(f"thread_num must be a positive number of threads, got {thread_num}")
        except BaseException:
            # Refused: destroy the node now, before the caller shuts rclpy down. Left to the garbage collector,
            # the half-built node's handles were finalized after rcl's shutdown and the process could crash
            # (SIGSEGV) on its way out instead of exiting with the refusal's status.
            self.supervisor.stop()
            self.destroy_node()
            raise
        self.executor_kind = executor_kind
        self._executor: ComponentExecutor = make_component_executor(
            executor_kind, self.context, thread_num, self._component_raised, self.supervisor.thread_died)
        self.intra_process_manager = IntraProcessManager(on_callback_error=self._component_raised,
                                                         make_wakeup=self._executor.make_wakeup)
        self._components: dict[int, LoadedComponent] = {}
        self._failed_components: dict[int, LoadedComponent] = {}  # delisted, waiting for the policy
        #: unloaded components' work going on (ComponentNode.work_left), by the name /diagnostics shows
        self._work_left: dict[str, Callable[[], Health | None]] = {}
        self._last_id = 0
        self._lock = threading.Lock()
        self._unload_lock = threading.Lock()  # the service thread and the supervisor never unload at once
        self.service_thread: threading.Thread | None = None
        group = MutuallyExclusiveCallbackGroup()
        self.create_service(LoadNode, "~/_container/load_node", self._on_load_node,
                            qos_profile=LOAD_UNLOAD_QOS, callback_group=group)
        self.create_service(UnloadNode, "~/_container/unload_node", self._on_unload_node,
                            qos_profile=LOAD_UNLOAD_QOS, callback_group=group)
        self.create_service(ListNodes, "~/_container/list_nodes", self._on_list_nodes, callback_group=group)
        # Not in rclcpp_components: this computer's clock and name, for fleet recording (its own group, so that
        # a slow load never delays the answer and spoils the round trip the offset is measured from).
        self.create_service(Trigger, CLOCK_SERVICE, self._on_clock,
                            callback_group=MutuallyExclusiveCallbackGroup())
        self._diagnostics = DiagnosticsPublisher(self, self._diagnostic_statuses)

    # --- service callbacks (each answers, whatever a component did) --------------------------------------
    def _on_load_node(self, request: LoadNode.Request, response: LoadNode.Response) -> LoadNode.Response:
        response.full_node_name, response.unique_id = "", 0
        try:
            loaded = self.load(request)
        except (LoadRequestError, PluginError, ComponentConstructionError) as exc:
            response.success, response.error_message = False, str(exc)
        except COMPONENT_ERRORS as exc:  # a bug on the load path: answer, log, stay up
            response.success, response.error_message = False, f"Internal error while loading: {exc!r}"
            self.get_logger().error("".join(traceback.format_exception(exc)))
        else:
            response.success, response.full_node_name = True, loaded.full_name
            # rclcpp leaves it empty on success and ros2 component ignores it then; ipc-component shows it.
            response.unique_id, response.error_message = loaded.unique_id, loaded.warning
            return response
        self.get_logger().error(f"Failed to load component {request.plugin_name}: {response.error_message}")
        return response

    def _on_unload_node(self, request: UnloadNode.Request,
                        response: UnloadNode.Response) -> UnloadNode.Response:
        try:
            result = self.unload(request.unique_id)
        except COMPONENT_ERRORS as exc:
            result = UnloadResult(True, f"Internal error while unloading: {exc!r}")
            self.get_logger().error("".join(traceback.format_exception(exc)))
        if not result.found:
            response.success = False
            response.error_message = f"No node found with unique_id: {request.unique_id}"
            self.get_logger().error(response.error_message)
        else:
            response.success, response.error_message = not result.error, result.error
        return response

    def _on_list_nodes(self, request: ListNodes.Request, response: ListNodes.Response) -> ListNodes.Response:
        self._reap_destroyed()
        for component in self.components():
            response.unique_ids.append(component.unique_id)
            response.full_node_names.append(component.full_name)
        return response

    def _on_clock(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """``message``: JSON of this computer's clock (``time_ns``, read last), host name and bag root."""
        response.success = True
        response.message = json.dumps({"host": socket.gethostname(),
                                       "bag_root": str(self.bag_root) if self.bag_root else "",
                                       "time_ns": time.time_ns()})
        return response

    # --- the load path -----------------------------------------------------------------------------------
    def load(self, request: LoadNode.Request, owner: int = 0) -> LoadedComponent:
        """Construct the requested component and start executing it; raises with the caller's message.

        ``owner``: the unique id of the component that asked for this one from its constructor (see
        :meth:`ComponentNode.load_owned_component`); an owned component is unloaded with its owner, first.
        """
        if self.exit_request.requested:
            raise LoadRequestError(f"The container is shutting down ({self.exit_request.reason}): load refused")
        node_class = self._registry.resolve(request.package_name, request.plugin_name)
        options = options_from_request(request, self._default_intra_process)
        kwargs = dict(options.node_kwargs, context=self.context,
                      parameter_overrides=_without_type_description_service(options.node_kwargs))
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
        node.shutdown_timeout = self.shutdown_timeout
        node.bag_root = self.bag_root
        if isinstance(node, ComponentNode):
            node.component_loader = functools.partial(self._load_owned, unique_id)
        try:
            node.__init__(**kwargs)
        except COMPONENT_ERRORS as exc:  # a component's constructor may raise anything; report it, stay up
            self._unload_owned(unique_id)
            _destroy_partially_constructed(node)
            raise ComponentConstructionError(f"Component constructor threw an exception: {exc}", str(exc)) from exc
        try:
            loaded = LoadedComponent(unique_id, node, request.package_name, request.plugin_name,
                                     node.get_fully_qualified_name(), options.log_level is not None, owner=owner)
            undeclared = undeclared_parameters(node, (p.name for p in request.parameters))
            if undeclared:
                loaded.warning = warning_text(loaded.full_name, undeclared)
                node.get_logger().warning(loaded.warning)
            if options.log_level is not None:
                node.get_logger().set_level(options.log_level)
            with self._lock:
                self._components[unique_id] = loaded
            self._executor.add(node)
        except COMPONENT_ERRORS as exc:  # the component cannot run: it must not stay listed
            with self._lock:
                self._components.pop(unique_id, None)
            self._executor.remove(node, 0.0)
            self._unload_owned(unique_id)
            _destroy_partially_constructed(node)
            raise ComponentConstructionError(f"Component could not be started: {exc}") from exc
        return loaded

    def _load_owned(self, owner: int, request: LoadNode.Request) -> Node:
        """A component's own load of another (from its constructor): listed like any, unloaded with it. A failure
        is the failed component's own reason: the owner's constructor reports it in its words, and the owner's
        load error then says "Component constructor threw an exception:" once, not once per level."""
        try:
            return self.load(request, owner).node
        except ComponentConstructionError as exc:
            raise ComponentConstructionError(exc.reason) from exc

    def _unload_owned(self, owner: int, timeout: float | None = None) -> None:
        """Tear down what component ``owner`` loaded, newest first (its own load failed or it is unloading),
        within ``timeout`` in all (default: ``shutdown_timeout``)."""
        deadline = time.monotonic() + (self.shutdown_timeout if timeout is None else timeout)
        with self._lock:
            owned = [self._components.pop(uid) for uid in sorted(self._components, reverse=True)
                     if self._components[uid].owner == owner]
        for loaded in owned:
            self._teardown(loaded, max(0.0, deadline - time.monotonic()))

    # --- the unload path ---------------------------------------------------------------------------------
    def unload(self, unique_id: int, timeout: float | None = None) -> UnloadResult:
        """Stop and destroy one component within ``timeout`` (default: ``shutdown_timeout``).

        The component leaves ListNodes first, then its callbacks are drained (no new ones start, running
        ones may finish), then its node is destroyed. A destroy that raises or overruns is reported in the
        result; the component is gone from the container either way.
        """
        with self._lock:
            loaded = self._components.pop(unique_id, None)
        if loaded is None:
            return UnloadResult(False)
        with self._unload_lock:
            return self._teardown(loaded, self.shutdown_timeout if timeout is None else timeout)

    def _teardown(self, loaded: LoadedComponent, timeout: float) -> UnloadResult:
        deadline = time.monotonic() + timeout
        self._unload_owned(loaded.unique_id, timeout / 2)  # first: what it loaded may still deliver to it
        self.get_logger().info(f"Unloading {loaded.full_name} (id {loaded.unique_id})")
        if not self._executor.remove(loaded.node, timeout):
            self.get_logger().warning(f"{loaded.full_name}: callbacks still running after {timeout:.1f} s; "
                                      "destroying it anyway")
        if loaded.logger_level_set:  # logger levels outlive nodes: the next node of that name starts clean
            loaded.node.get_logger().set_level(LoggingSeverity.UNSET)
        error = _destroy_within(loaded.node, max(0.0, deadline - time.monotonic()))
        work_left = getattr(loaded.node, "work_left", None)
        if work_left is not None and work_left() is not None:
            with self._lock:
                self._work_left[f"{loaded.full_name} (unloaded, id {loaded.unique_id})"] = work_left
        if error:
            error = f"Unloading {loaded.full_name} (id {loaded.unique_id}): {error}"
            self.get_logger().error(error)
        return UnloadResult(True, error)

    def _component_raised(self, node: Node, exc: BaseException) -> None:
        """A callback of ``node`` raised (called in the thread where it did): delist it, apply the policy."""
        with self._lock:
            loaded = next((c for c in self._components.values() if c.node is node), None)
            if loaded is not None:
                del self._components[loaded.unique_id]
                self._failed_components[loaded.unique_id] = loaded
        if loaded is None:  # a component already leaving (e.g. InvalidHandle after a drain timeout)
            return
        reason = f"{type(exc).__name__}: {exc}".splitlines()[0] if str(exc) else type(exc).__name__
        self.supervisor.component_failed(ComponentFailure(loaded.unique_id, loaded.full_name, reason), exc)

    def _reap_destroyed(self) -> None:
        """A component that destroyed its own node is not running any more: it fails like one that raised."""
        for component in self.components():
            if not _node_alive(component.node):
                self._component_raised(component.node, RuntimeError("its node was destroyed while it was loaded"))

    def _unload_failed(self, unique_id: int, reason: str) -> None:
        """The ``unload`` policy: tear down a component that :meth:`_component_raised` delisted."""
        with self._lock:
            loaded = self._failed_components.pop(unique_id, None)
        if loaded is not None:
            with self._unload_lock:
                self._teardown(loaded, self.shutdown_timeout)

    def components(self) -> list[LoadedComponent]:
        """The loaded (running) components in ascending id order."""
        with self._lock:
            return [self._components[uid] for uid in sorted(self._components)]

    def shutdown(self, timeout: float | None = None) -> bool:
        """Unload every component, newest first (so recorders finalize), within ``timeout`` in all; then
        stop the threads. False if some component could not be unloaded cleanly in time."""
        deadline = time.monotonic() + (self.shutdown_timeout if timeout is None else timeout)
        clean = True
        self.supervisor.stop()
        for failed_id in list(self._failed_components):
            self._unload_failed(failed_id, "")
        for component in reversed(self.components()):
            result = self.unload(component.unique_id, max(0.0, deadline - time.monotonic()))
            clean = clean and not result.error
        self._diagnostics.stop()
        self._executor.shutdown(max(0.0, deadline - time.monotonic()))
        return clean

    # --- health ------------------------------------------------------------------------------------------
    def threads(self) -> dict[str, threading.Thread]:
        """The container's own threads, by name."""
        threads = {thread.name: thread for thread in self._executor.threads()}
        if self.service_thread is not None:
            threads["component_manager"] = self.service_thread
        return threads

    def _diagnostic_statuses(self) -> list[DiagnosticStatus]:
        self._reap_destroyed()
        prefix = self.get_fully_qualified_name()
        components = self.components()
        now_ns = time.monotonic_ns()  # the instant the publish counts are read at (publish_counts.UPTIME)
        container = threads_health(self.threads())
        if not self.supervisor.alive():
            container = Health(ERROR, "supervisor thread died", container.values)
        container.values.update({"executor": self.executor_kind, "components": str(len(components)),
                                 "on_component_error": self.supervisor.policy,
                                 UPTIME: f"{(now_ns - self._started_ns) / 1e9:.6f}", **self._free_disk()})
        statuses = [status(f"{prefix}: container", container)]
        for component in components:
            health = component_health(component.node)
            counters = getattr(component.node, "publish_counters", None)
            health.values = {"unique_id": str(component.unique_id), "plugin": component.plugin_name,
                             **health.values, **publication_values(counters() if counters else (), now_ns)}
            statuses.append(status(f"{prefix}: {component.full_name}", health))
        running = {component.full_name for component in components}
        for failure in self.supervisor.failures:
            if failure.full_name not in running:
                statuses.append(status(f"{prefix}: {failure.full_name}", Health(
                    ERROR, f"failed and unloaded: {failure.reason}", {"unique_id": str(failure.unique_id)})))
        with self._lock:
            work_left = list(self._work_left.items())
        for name, work in work_left:
            health = work()
            if health is None:
                with self._lock:
                    self._work_left.pop(name, None)
            else:
                statuses.append(status(f"{prefix}: {name}", health))
        return statuses

    def _free_disk(self) -> dict[str, str]:
        """The free space where components' relative paths go (the bag root, or the working directory)."""
        try:
            free = shutil.disk_usage(self.bag_root or os.getcwd()).free
        except OSError:  # the directory is gone: nothing to report
            return {}
        return {FREE_DISK_MB: f"{free / 1e6:.0f}"}


class ComponentConstructionError(Exception):
    """The component's constructor raised (or the component could not be started); ``reason`` is the message
    without the container's own words (the constructor's exception text, when it raised)."""

    def __init__(self, message: str, reason: str | None = None) -> None:
        super().__init__(message)
        self.reason = message if reason is None else reason


def _destroy_partially_constructed(node: Node) -> None:
    """Destroy what a failed component constructor created; a node that never got an rcl handle is ignored."""
    try:
        node.destroy_node()
    except Exception:  # noqa: BLE001 - __init__ failed before the node existed, or half-way through it
        pass


def _without_type_description_service(node_kwargs: dict[str, Any]) -> list[Parameter]:
    """The request's parameter overrides, with ``start_type_description_service`` false unless it says so.

    rclpy 7.1.6 leaks about 105 kB of native memory per node whose ``~/get_type_description`` service is
    created and destroyed (nothing without the service), so a container that loads and unloads components for
    days would grow without bound. A load request that wants the service sets the parameter to true.
    """
    overrides = list(node_kwargs.get("parameter_overrides") or [])
    if not any(p.name == TYPE_DESCRIPTION_SERVICE_PARAMETER for p in overrides):
        overrides.append(Parameter(TYPE_DESCRIPTION_SERVICE_PARAMETER, value=False))
    return overrides


def _node_alive(node: Node) -> bool:
    try:
        with node.handle:
            return True
    except InvalidHandle:
        return False


def _destroy_within(node: Node, timeout: float) -> str:
    """Run the component's ``destroy_node`` on a helper thread for at most ``timeout`` s; '' if it went well.

    If the component's own ``destroy_node`` raises, the base classes' is run as well, so its DDS entities and
    intra-process registrations do not linger. One that overruns is abandoned (a daemon thread), with an error.
    """
    errors: list[str] = []

    def destroy() -> None:
        try:
            node.destroy_node()
        except COMPONENT_ERRORS as exc:
            errors.append(f"its destroy_node raised {type(exc).__name__}: {exc}; its node was destroyed anyway")
            base = ComponentNode if isinstance(node, ComponentNode) else Node
            try:
                base.destroy_node(node)
            except COMPONENT_ERRORS as base_exc:
                errors.append(f"destroying its node failed too: {base_exc}")

    thread = threading.Thread(target=destroy, name="unload", daemon=True)
    thread.start()
    thread.join(timeout)
    if thread.is_alive():
        return (f"did not finish within {timeout:.1f} s (shutdown timeout); it was abandoned and may have "
                "left work unfinished (a recorder's bag can be repaired)")
    return "; ".join(errors)
