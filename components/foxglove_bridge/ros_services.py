"""The graph's ROS services for Foxglove clients: advertised with their request and response definitions,
called with CDR.

Each service of the graph (within ``service_whitelist``) is advertised as ``foxglove_bridge`` does: its type
as the schema name, request and response as ``ros2msg`` definitions (``pkg/srv/Name_Request`` /
``_Response``, baglib.format.message_definitions), encoding ``cdr``. A call arrives on one of the SDK's
threads with the request's CDR: it is deserialized, called through a client of the bridge node on the
executor (executor_work), and the response goes back as CDR; one that does not come within
:data:`SERVICE_TIMEOUT` is a failed call.
"""
from __future__ import annotations

import importlib
import time
from typing import Any, Callable

import foxglove
from foxglove import MessageSchema, Schema, Service, ServiceRequest, ServiceSchema
from rclpy.node import Node
from rclpy.serialization import deserialize_message

from baglib.format.message_definitions import service_definitions
from components.foxglove_bridge.bridge_options import BridgeOptions
from components.foxglove_bridge.executor_work import Work, WorkQueue
from components.foxglove_bridge.channel_registry import cdr_bytes

#: s a Foxglove service call waits for the ROS service's response
SERVICE_TIMEOUT = 10.0
#: s a call waits for a new client to match its service
READY_WAIT = 2.0


def service_class(type_name: str) -> Any:
    package, _, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.srv"), name)


def service_schema(type_name: str) -> ServiceSchema:
    request, response = service_definitions(type_name)
    return ServiceSchema(
        name=type_name,
        request=MessageSchema(encoding="cdr", schema=Schema(name=f"{type_name}_Request", encoding="ros2msg",
                                                            data=request.encode())),
        response=MessageSchema(encoding="cdr", schema=Schema(name=f"{type_name}_Response", encoding="ros2msg",
                                                             data=response.encode())))


class RosServices:
    """The advertised services (name -> type) and their clients on the bridge node."""

    def __init__(self, node: Node, options: BridgeOptions, work: WorkQueue, server: Any,
                 warn: Callable[[str], None]) -> None:
        self._node = node
        self._options = options
        self._work = work
        self._server = server
        self._warn = warn
        self._advertised: dict[str, str] = {}
        self._ignored: set[tuple[str, tuple[str, ...]]] = set()
        self._clients: dict[str, Any] = {}

    # --- the executor ---------------------------------------------------------------------------------------
    def sync(self, services_and_types: list[tuple[str, list[str]]]) -> None:
        """Advertise the graph's new services; withdraw those gone (or changed type)."""
        current = {name: tuple(types) for name, types in services_and_types if self._options.offers_service(name)}
        gone = [name for name, type_name in self._advertised.items() if current.get(name) != (type_name,)]
        if gone:
            self._server.remove_services(gone)
            for name in gone:
                del self._advertised[name]
                client = self._clients.pop(name, None)
                if client is not None:
                    self._node.destroy_client(client)
        new = [self._service(name, types) for name, types in current.items()
               if name not in self._advertised and (name, types) not in self._ignored]
        if any(new):
            self._server.add_services([service for service in new if service is not None])

    def _service(self, name: str, types: tuple[str, ...]) -> foxglove.Service | None:
        try:
            if len(types) != 1:
                raise ValueError(f"it has more than one type ({', '.join(types)})")
            schema = service_schema(types[0])
            service_class(types[0])
        except Exception as exc:  # noqa: BLE001 - any type this environment cannot call: that service only
            self._ignored.add((name, types))
            self._warn(f"Not offering service {name}: {type(exc).__name__}: {exc}")
            return None
        self._advertised[name] = types[0]
        return Service(name, schema=schema, handler=lambda request: self._handle(name, types[0], request))

    def _call(self, name: str, type_name: str, request: Any, deadline: float) -> Callable[[Work], bool]:
        """A work step that calls the service once its client matched it (or READY_WAIT passed)."""
        def step(work: Work) -> bool:
            client = self._clients.get(name)
            if client is None:
                client = self._clients[name] = self._node.create_client(service_class(type_name), name)
            if not client.service_is_ready() and time.monotonic() < deadline:
                return False
            work.expect()
            future = client.call_async(request)
            future.add_done_callback(lambda done: work.add(
                [done.result()] if not done.cancelled() and done.exception() is None else []))
            return True
        return step

    # --- the SDK's threads ----------------------------------------------------------------------------------
    def _handle(self, name: str, type_name: str, request: ServiceRequest) -> bytes:
        """One call from a client: its CDR request in, the CDR response out (or an error the SDK reports)."""
        if request.encoding != "cdr":
            raise ValueError(f"unsupported encoding {request.encoding!r} (the bridge speaks cdr)")
        message = deserialize_message(request.payload, service_class(type_name).Request)
        responses = self._work.submit(self._call(name, type_name, message, time.monotonic() + READY_WAIT),
                                      SERVICE_TIMEOUT)
        if not responses:
            raise TimeoutError(f"no response from {name} within {SERVICE_TIMEOUT:g} s")
        return cdr_bytes(responses[0])

    def close(self) -> None:
        for client in self._clients.values():
            self._node.destroy_client(client)
        self._clients.clear()
