"""Action introspection on Jazzy: the service events Kilted's rcl_action publishes, from rclpy action servers and
clients. On Kilted, :func:`action_server` and :func:`action_client` return rclpy's own, whose
``configure_introspection`` has rcl_action publish the same events.

Kilted's ``ActionServer.configure_introspection(clock, qos, state)`` (and the client's) make the action's three
services publish their requests and responses as service events, on ``<action>/_action/send_goal/_service_event``,
``.../cancel_goal/_service_event`` and ``.../get_result/_service_event``, typed ``<pkg>/action/<Name>_SendGoal_Event``,
``action_msgs/srv/CancelGoal_Event`` and ``<pkg>/action/<Name>_GetResult_Event``. rosbag2 Kilted records them with
``--actions`` and replays the goals from them. Jazzy's rcl_action has no introspection; the event types exist in the
Jazzy interface packages, so the classes here publish the same events from Python:

* a server publishes ``REQUEST_RECEIVED`` for every request it takes and ``RESPONSE_SENT`` for every response;
* a client publishes ``REQUEST_SENT`` for every request and ``RESPONSE_RECEIVED`` for every response it takes;
* each with the request's sequence number and the configured clock's time; ``METADATA`` leaves request and
  response out, ``OFF`` (the default, as in Kilted) publishes nothing.

``client_gid`` stays zero: rclpy Jazzy exposes neither a request's writer GID nor a client's. rosbag2's player
does not need it to replay goals (it reads the request events of one side, see docs/player.md).

The responses are seen by replacing the rclpy handle with a Python subclass of it whose ``send_*`` methods publish
too: rclpy's ``ActionServer`` / ``ActionClient`` constructors create their handle themselves, so a second one is
made right after and the first destroyed before the action is returned to its creator.
"""
from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

from rclpy.action import ActionClient, ActionServer
from rclpy.clock import Clock
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.service_introspection import ServiceIntrospectionState
from service_msgs.msg import ServiceEventInfo

from baglib.format.action_topics import INTERFACES

__all__ = ["IntrospectedActionClient", "IntrospectedActionServer", "ServiceIntrospectionState", "action_client",
           "action_server"]

#: rclpy 9 (Kilted) on: rcl_action publishes the events itself and rclpy's own server and client configure it.
NATIVE_INTROSPECTION = hasattr(ActionServer, "configure_introspection")

# the Impl service of each interface and the keys rclpy's take_data uses for it
_SERVICES = {"send_goal": ("SendGoalService", "goal"), "cancel_goal": ("CancelGoalService", "cancel"),
             "get_result": ("GetResultService", "result")}


class _ActionEvents:
    """The three service event publishers of one action endpoint, and its introspection state."""

    def __init__(self, node: Node, action_type: Any, action_name: str) -> None:
        self._node = node
        self._action_type = action_type
        self._topics = {interface: node.resolve_topic_name(action_name) + INTERFACES[interface]
                        for interface in _SERVICES}
        self._publishers: dict[str, Any] = {}
        self._clock: Clock | None = None
        self._state = ServiceIntrospectionState.OFF

    def configure(self, clock: Clock, qos: QoSProfile, state: ServiceIntrospectionState) -> None:
        """Kilted's ``configure_introspection``: publishers exist while the state is not OFF."""
        if state == ServiceIntrospectionState.OFF:
            for publisher in self._publishers.values():
                self._node.destroy_publisher(publisher)
            self._publishers = {}
        elif not self._publishers:
            self._publishers = {
                interface: self._node.create_publisher(self._event_class(interface), self._topics[interface], qos)
                for interface in _SERVICES}
        self._clock, self._state = clock, state

    def _event_class(self, interface: str) -> Any:
        return getattr(self._action_type.Impl, _SERVICES[interface][0]).Event

    def publish(self, interface: str, event_type: int, sequence_number: int, request: Any = None,
                response: Any = None) -> None:
        """One event; nothing while OFF, no request or response with METADATA."""
        if self._state == ServiceIntrospectionState.OFF or self._clock is None:
            return
        event = self._event_class(interface)()
        event.info = ServiceEventInfo(event_type=event_type, stamp=self._clock.now().to_msg(),
                                      sequence_number=sequence_number)
        if self._state == ServiceIntrospectionState.CONTENTS:
            event.request = [request] if request is not None else []
            event.response = [response] if response is not None else []
        self._publishers[interface].publish(event)

    def destroy(self) -> None:
        self.configure(Clock(), QoSProfile(depth=1), ServiceIntrospectionState.OFF)


class _ServerHandle(_rclpy.ActionServer):  # type: ignore[misc,name-defined]
    """rclpy's action server handle; every response it sends is also published as a RESPONSE_SENT event."""

    events: _ActionEvents

    def send_goal_response(self, header: Any, response: Any) -> None:
        super().send_goal_response(header, response)
        self.events.publish("send_goal", ServiceEventInfo.RESPONSE_SENT, header.sequence_number, response=response)

    def send_cancel_response(self, header: Any, response: Any) -> None:
        super().send_cancel_response(header, response)
        self.events.publish("cancel_goal", ServiceEventInfo.RESPONSE_SENT, header.sequence_number,
                            response=response)

    def send_result_response(self, header: Any, response: Any) -> None:
        super().send_result_response(header, response)
        self.events.publish("get_result", ServiceEventInfo.RESPONSE_SENT, header.sequence_number,
                            response=response)


class _ClientHandle(_rclpy.ActionClient):  # type: ignore[misc,name-defined]
    """rclpy's action client handle; every request it sends is also published as a REQUEST_SENT event."""

    events: _ActionEvents

    def _sent(self, interface: str, sequence_number: int, request: Any) -> int:
        self.events.publish(interface, ServiceEventInfo.REQUEST_SENT, sequence_number, request=request)
        return sequence_number

    def send_goal_request(self, request: Any) -> int:
        return self._sent("send_goal", super().send_goal_request(request), request)

    def send_cancel_request(self, request: Any) -> int:
        return self._sent("cancel_goal", super().send_cancel_request(request), request)

    def send_result_request(self, request: Any) -> int:
        return self._sent("get_result", super().send_result_request(request), request)


def _constructor_arguments(cls: type, args: tuple[Any, ...], kwargs: dict[str, Any]) -> dict[str, Any]:
    """Every argument of ``cls.__init__`` as it was called, defaults filled in."""
    bound = inspect.signature(cls.__init__).bind(None, *args, **kwargs)
    bound.apply_defaults()
    return dict(bound.arguments)


def _swap(endpoint: Any, attribute: str, make: Callable[[], Any], events: _ActionEvents) -> None:
    """Replace the endpoint's rclpy handle by ``make()`` (a handle subclass) and destroy the one rclpy made."""
    handle = make()
    handle.events = events
    old = getattr(endpoint, attribute)
    setattr(endpoint, attribute, handle)
    old.destroy_when_not_in_use()


class _Introspectable:
    """Kilted's ``configure_introspection`` on an action server or client whose ``_events`` publish."""

    _events: _ActionEvents

    def configure_introspection(self, clock: Clock, service_event_qos_profile: QoSProfile,
                                introspection_state: ServiceIntrospectionState) -> None:
        """Publish the action's service events (Kilted's ``configure_introspection``)."""
        self._events.configure(clock, service_event_qos_profile, introspection_state)

    def destroy(self) -> None:
        self._events.destroy()
        super().destroy()  # type: ignore[misc]


class IntrospectedActionServer(_Introspectable, ActionServer):
    """rclpy's ``ActionServer`` with Kilted's ``configure_introspection`` (see module doc)."""

    def __init__(self, node: Node, action_type: Any, action_name: str, execute_callback: Callable[..., Any],
                 **kwargs: Any) -> None:
        super().__init__(node, action_type, action_name, execute_callback, **kwargs)
        a = _constructor_arguments(ActionServer, (node, action_type, action_name, execute_callback), kwargs)
        self._events = _ActionEvents(node, action_type, action_name)
        with self._lock, node.handle, node.get_clock().handle:
            _swap(self, "_handle", lambda: _ServerHandle(
                node.handle, node.get_clock().handle, action_type, action_name,
                a["goal_service_qos_profile"].get_c_qos_profile(),
                a["result_service_qos_profile"].get_c_qos_profile(),
                a["cancel_service_qos_profile"].get_c_qos_profile(),
                a["feedback_pub_qos_profile"].get_c_qos_profile(),
                a["status_pub_qos_profile"].get_c_qos_profile(),
                a["result_timeout"]), self._events)

    def take_data(self) -> dict[str, Any]:
        data = super().take_data()
        for interface, (_, key) in _SERVICES.items():
            if key in data:
                header, request = data[key]
                self._events.publish(interface, ServiceEventInfo.REQUEST_RECEIVED, header.sequence_number,
                                     request=request)
        return data


class IntrospectedActionClient(_Introspectable, ActionClient):
    """rclpy's ``ActionClient`` with Kilted's ``configure_introspection`` (see module doc)."""

    def __init__(self, node: Node, action_type: Any, action_name: str, **kwargs: Any) -> None:
        super().__init__(node, action_type, action_name, **kwargs)
        a = _constructor_arguments(ActionClient, (node, action_type, action_name), kwargs)
        self._events = _ActionEvents(node, action_type, action_name)
        with node.handle:
            _swap(self, "_client_handle", lambda: _ClientHandle(
                node.handle, action_type, action_name,
                a["goal_service_qos_profile"].get_c_qos_profile(),
                a["result_service_qos_profile"].get_c_qos_profile(),
                a["cancel_service_qos_profile"].get_c_qos_profile(),
                a["feedback_sub_qos_profile"].get_c_qos_profile(),
                a["status_sub_qos_profile"].get_c_qos_profile()), self._events)

    def take_data(self) -> dict[str, Any]:
        data = super().take_data()
        for interface, (_, key) in _SERVICES.items():
            if key in data:
                sequence_number, response = data[key]
                self._events.publish(interface, ServiceEventInfo.RESPONSE_RECEIVED, sequence_number,
                                     response=response)
        return data


def action_server(node: Node, action_type: Any, action_name: str, execute_callback: Callable[..., Any],
                  **kwargs: Any) -> ActionServer:
    """An action server with ``configure_introspection``: rclpy's own where rcl_action introspects (Kilted on),
    else :class:`IntrospectedActionServer`; the same topics, types and events either way."""
    kind = ActionServer if NATIVE_INTROSPECTION else IntrospectedActionServer
    return kind(node, action_type, action_name, execute_callback, **kwargs)


def action_client(node: Node, action_type: Any, action_name: str, **kwargs: Any) -> ActionClient:
    """An action client with ``configure_introspection``, chosen as :func:`action_server`."""
    kind = ActionClient if NATIVE_INTROSPECTION else IntrospectedActionClient
    return kind(node, action_type, action_name, **kwargs)
