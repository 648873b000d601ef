"""Parameters of the graph's nodes for Foxglove clients: list, get and set, named ``/node.parameter``.

As ``foxglove_bridge`` does, through each node's own parameter services (``~/list_parameters``,
``~/get_parameters``, ``~/set_parameters``): the components of the bridge's container, and any other node of
the domain, filtered by ``param_whitelist``. The calls are asynchronous, on the executor (see executor_work);
a client waits at most :data:`PARAMETER_TIMEOUT` for them and gets what answered by then. Changes a node
announces on ``/parameter_events`` go to the clients subscribed to those parameters.
"""
from __future__ import annotations

import time
from array import array
from collections import defaultdict
from typing import Any, Callable

import foxglove
from foxglove import ParameterType as FoxgloveType
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterEvent, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, ListParameters, SetParameters
from rclpy.node import Node
from rclpy.parameter import parameter_value_to_python

from components.foxglove_bridge.bridge_options import BridgeOptions
from components.foxglove_bridge.executor_work import Work, WorkQueue

#: s a client's get or set waits for the nodes' answers
PARAMETER_TIMEOUT = 2.0
#: s a request waits for the service clients it needed to create to match their services
READY_WAIT = 1.0


def to_foxglove(name: str, value: ParameterValue) -> foxglove.Parameter:
    """A ROS parameter value as the Foxglove protocol carries it (doubles keep their type)."""
    python = parameter_value_to_python(value)
    if value.type == ParameterType.PARAMETER_NOT_SET:
        return foxglove.Parameter(name)
    if value.type == ParameterType.PARAMETER_DOUBLE:
        return foxglove.Parameter(name, value=float(python), type=FoxgloveType.Float64)
    if value.type == ParameterType.PARAMETER_DOUBLE_ARRAY:
        return foxglove.Parameter(name, value=[float(v) for v in python], type=FoxgloveType.Float64Array)
    if value.type == ParameterType.PARAMETER_BYTE_ARRAY:
        return foxglove.Parameter(name, value=b"".join(python), type=FoxgloveType.ByteArray)
    if isinstance(python, (list, tuple, array)):
        return foxglove.Parameter(name, value=list(python))
    return foxglove.Parameter(name, value=python)


def to_ros(value: Any, hint: FoxgloveType | None, current: int | None) -> ParameterValue | None:
    """A Foxglove parameter value as a ROS one; numbers follow the parameter's current type (a whole-valued
    double arrives as an integer). None for what ROS cannot hold (a dict, a mixed list)."""
    doubles = hint in (FoxgloveType.Float64, FoxgloveType.Float64Array) or current in (
        ParameterType.PARAMETER_DOUBLE, ParameterType.PARAMETER_DOUBLE_ARRAY)
    if isinstance(value, bool):
        return ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value)
    if isinstance(value, (int, float)):
        if doubles or isinstance(value, float):
            return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(value))
        return ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)
    if isinstance(value, str):
        return ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
    if isinstance(value, bytes):
        return ParameterValue(type=ParameterType.PARAMETER_BYTE_ARRAY, byte_array_value=[bytes([b]) for b in value])
    if isinstance(value, list):
        return _array(value, doubles)
    return None


def _array(values: list[Any], doubles: bool) -> ParameterValue | None:
    if all(isinstance(v, bool) for v in values):
        return ParameterValue(type=ParameterType.PARAMETER_BOOL_ARRAY, bool_array_value=values)
    if all(isinstance(v, int) and not isinstance(v, bool) for v in values) and not doubles:
        return ParameterValue(type=ParameterType.PARAMETER_INTEGER_ARRAY, integer_array_value=values)
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return ParameterValue(type=ParameterType.PARAMETER_DOUBLE_ARRAY, double_array_value=[float(v) for v in values])
    if all(isinstance(v, str) for v in values):
        return ParameterValue(type=ParameterType.PARAMETER_STRING_ARRAY, string_array_value=values)
    return None


def split_name(name: str) -> tuple[str, str]:
    """``/ns/node.param.name`` -> (``/ns/node``, ``param.name``); node names never hold a dot."""
    node, _, parameter = name.partition(".")
    return node, parameter


class _NodeClients:
    def __init__(self, node: Node, target: str) -> None:
        self.list = node.create_client(ListParameters, f"{target}/list_parameters")
        self.get = node.create_client(GetParameters, f"{target}/get_parameters")
        self.set = node.create_client(SetParameters, f"{target}/set_parameters")

    def ready(self) -> bool:
        return all(c.service_is_ready() for c in (self.list, self.get, self.set))

    def destroy(self, node: Node) -> None:
        for client in (self.list, self.get, self.set):
            node.destroy_client(client)


class RosParameters:
    """The listener's parameter requests, answered through the nodes' parameter services."""

    def __init__(self, node: Node, options: BridgeOptions, work: WorkQueue,
                 publish: Callable[[list[foxglove.Parameter]], None]) -> None:
        self._node = node
        self._options = options
        self._work = work
        self._publish = publish
        self._clients: dict[str, _NodeClients] = {}
        self._events = node.create_subscription(ParameterEvent, "/parameter_events", self._on_event, 100)

    # --- the SDK's threads ----------------------------------------------------------------------------------
    def get(self, names: list[str]) -> list[foxglove.Parameter]:
        """The values of ``names`` (all parameters of all nodes when empty) that answered in time."""
        wanted = [n for n in names if self._options.exposes_parameter(n)]
        if names and not wanted:
            return []
        return self._work.submit(self._stepper(lambda work, targets: self._get(work, targets), wanted),
                                 PARAMETER_TIMEOUT)

    def set(self, parameters: list[foxglove.Parameter]) -> list[foxglove.Parameter]:
        """Set ``parameters``; returns their values afterwards (a refused one keeps its old value)."""
        values = {p.name: (p.get_value(), p.type) for p in parameters if self._options.exposes_parameter(p.name)}
        return self._work.submit(self._stepper(lambda work, targets: self._set(work, targets, values),
                                               list(values)), PARAMETER_TIMEOUT)

    # --- the executor ---------------------------------------------------------------------------------------
    def _stepper(self, start: Callable[[Work, dict[str, list[str] | None]], None],
                 names: list[str]) -> Callable[[Work], bool]:
        """A work step that starts ``start`` once the clients of the target nodes are ready (or READY_WAIT
        passed: nodes still not ready are left out)."""
        deadline: list[float] = []

        def step(work: Work) -> bool:
            targets = self._targets(names)
            deadline[:] = deadline or [time.monotonic() + READY_WAIT]
            ready = {node: params for node, params in targets.items() if self._clients_of(node).ready()}
            if len(ready) < len(targets) and time.monotonic() < deadline[0]:
                return False
            if not ready:
                work.finish()
            start(work, ready)
            return True
        return step

    def _targets(self, names: list[str]) -> dict[str, list[str] | None]:
        """node -> its parameter names asked for (None: all of them)."""
        if not names:
            return {f"{ns.rstrip('/')}/{name}": None for name, ns in self._node.get_node_names_and_namespaces()
                    if not name.startswith("_")}
        grouped: dict[str, list[str]] = defaultdict(list)
        for name in names:
            node, parameter = split_name(name)
            grouped[node].append(parameter)
        return dict(grouped)

    def _clients_of(self, target: str) -> _NodeClients:
        clients = self._clients.get(target)
        if clients is None:
            clients = self._clients[target] = _NodeClients(self._node, target)
        return clients

    def _get(self, work: Work, targets: dict[str, list[str] | None]) -> None:
        work.expect(len(targets))
        for target, names in targets.items():
            if names is None:
                request = ListParameters.Request(depth=ListParameters.Request.DEPTH_RECURSIVE)
                self._call(work, self._clients[target].list, request,
                           lambda response, t=target: self._fetch(work, t, list(response.result.names)))
            else:
                self._fetch(work, target, names)

    def _fetch(self, work: Work, target: str, names: list[str]) -> None:
        self._call(work, self._clients[target].get, GetParameters.Request(names=names),
                   lambda response: work.add(self._named(target, names, response.values)))

    def _set(self, work: Work, targets: dict[str, list[str] | None],
             values: dict[str, tuple[Any, FoxgloveType | None]]) -> None:
        work.expect(len(targets))
        for target, names in targets.items():
            names = names or []
            self._call(work, self._clients[target].get, GetParameters.Request(names=names),
                       lambda response, t=target, n=names: self._set_node(work, t, n, response.values, values))

    def _set_node(self, work: Work, target: str, names: list[str], current: list[ParameterValue],
                  values: dict[str, tuple[Any, FoxgloveType | None]]) -> None:
        messages = []
        for name, old in zip(names, current):
            value, hint = values[f"{target}.{name}"]
            new = to_ros(value, hint, old.type)
            if new is not None:
                messages.append(ParameterMsg(name=name, value=new))
        self._call(work, self._clients[target].set, SetParameters.Request(parameters=messages),
                   lambda _response: self._fetch(work, target, names))

    def _call(self, work: Work, client: Any, request: Any, then: Callable[[Any], None]) -> None:
        """Call asynchronously; ``then(response)`` on the executor, or the node counts as answered empty."""
        future = client.call_async(request)

        def done(finished: Any) -> None:
            response = finished.result() if not finished.cancelled() and finished.exception() is None else None
            if response is None:
                work.add([])
            else:
                then(response)
        future.add_done_callback(done)

    def _named(self, target: str, names: list[str], values: list[ParameterValue]) -> list[foxglove.Parameter]:
        return [to_foxglove(f"{target}.{name}", value) for name, value in zip(names, values)
                if self._options.exposes_parameter(f"{target}.{name}")]

    def _on_event(self, event: ParameterEvent) -> None:
        changed = [to_foxglove(f"{event.node}.{p.name}", p.value)
                   for p in [*event.new_parameters, *event.changed_parameters]
                   if self._options.exposes_parameter(f"{event.node}.{p.name}")]
        if changed:
            self._publish(changed)

    def prune(self, nodes: set[str]) -> None:
        """Forget the clients of nodes that left the graph."""
        for target in [t for t in self._clients if t not in nodes]:
            self._clients.pop(target).destroy(self._node)

    def close(self) -> None:
        self.prune(set())
        self._node.destroy_subscription(self._events)
