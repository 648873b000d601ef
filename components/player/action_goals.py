"""``play.send_actions_as_client``: recorded action goals sent to the live action server, as rosbag2 Kilted does
(ros2/rosbag2#1955, rosbag2_transport's PlayerActionClient).

Instead of publishing an action's recorded topics, the player is a client of the action: each recorded
``send_goal`` request event becomes a goal sent with the recorded goal and goal id; each ``cancel_goal`` and
``get_result`` request event a cancel or result request for its goal id. The requests are the events the server
received (``SERVICE_INTROSPECTION``, the default) or the ones clients sent (``CLIENT_INTROSPECTION``), as for
services. Feedback and status are not published: the server makes them. As in rosbag2:

* an accepted goal's result is requested at once (rclcpp's result callback), and the goal is forgotten when it
  arrives; a cancel or result request for a goal not (yet) accepted waits until it is;
* events recorded with metadata-only introspection carry no request: skipped with one warning;
* while the server is not available each request is skipped with an error.
"""
from __future__ import annotations

import importlib
import threading
from typing import Any

from rclpy.action import ActionClient
from rclpy.node import Node

from baglib.format.action_topics import action_interface, action_name, action_type, is_action_topic
from baglib.format.cdr_read import deserialize
from baglib.format.message_definitions import message_class
from baglib.read.reader import Connection
from components.player.service_requests import REQUEST_EVENTS


def action_class(action_type_name: str) -> Any:
    """``pkg/action/Name`` -> the Python action class (ImportError / AttributeError when not installed)."""
    package, _, name = action_type_name.split("/")
    return getattr(importlib.import_module(f"{package}.action"), name)


class ActionGoalReplay:
    """One recorded action's client in the player, shared by its three service event topics."""

    def __init__(self, node: Node, action: str, action_type_name: str, source: str) -> None:
        self.action = action
        self.client = ActionClient(node, action_class(action_type_name), action)
        self._wanted = REQUEST_EVENTS[source]
        self._logger = node.get_logger()
        self._lock = threading.Lock()
        self._handles: dict[bytes, Any] = {}  # accepted goals whose result has not arrived
        self._postponed_cancel: set[bytes] = set()
        self._postponed_result: set[bytes] = set()
        self._warned_metadata_only = False

    def send(self, interface: str, event: Any) -> bool:
        """Send the request ``event`` carries; False when it is not one to send (see module doc)."""
        if event.info.event_type != self._wanted:
            return False
        if not event.request:
            if not self._warned_metadata_only:
                self._warned_metadata_only = True
                self._logger.warning(f"Can't send {interface} request since the configuration of introspection "
                                     f"for '{self.action}' action was metadata !")
            return False
        if not self.client.server_is_ready():
            self._logger.error(f"Action request hasn't been sent. The '{self.action}' action server isn't ready !")
            return False
        request = event.request[0]
        if interface == "send_goal":
            future = self.client.send_goal_async(request.goal, goal_uuid=request.goal_id)
            future.add_done_callback(self._on_goal_response)
        elif interface == "cancel_goal":
            self._for_goal(bytes(request.goal_info.goal_id.uuid), self._postponed_cancel, self._cancel)
        else:
            self._for_goal(bytes(request.goal_id.uuid), self._postponed_result, self._request_result)
        return True

    def _for_goal(self, goal_id: bytes, postponed: set[bytes], act: Any) -> None:
        with self._lock:
            handle = self._handles.get(goal_id)
            if handle is None:
                postponed.add(goal_id)  # the goal may not be accepted yet
                return
        act(handle)

    def _on_goal_response(self, future: Any) -> None:
        handle = future.result()
        if handle is None or not handle.accepted:
            return
        goal_id = bytes(handle.goal_id.uuid)
        with self._lock:
            cancel = goal_id in self._postponed_cancel
            self._postponed_cancel.discard(goal_id)
            self._postponed_result.discard(goal_id)  # the result is requested below anyway
            if not cancel:
                self._handles[goal_id] = handle
        if cancel:
            self._cancel(handle)
        else:
            self._request_result(handle)

    def _cancel(self, handle: Any) -> None:
        with self._lock:
            self._handles.pop(bytes(handle.goal_id.uuid), None)
        handle.cancel_goal_async()

    def _request_result(self, handle: Any) -> None:
        goal_id = bytes(handle.goal_id.uuid)
        handle.get_result_async().add_done_callback(lambda _: self._forget(goal_id))

    def _forget(self, goal_id: bytes) -> None:
        with self._lock:
            self._handles.pop(goal_id, None)

    def in_progress(self) -> int:
        """Accepted goals whose result has not arrived yet."""
        with self._lock:
            return len(self._handles)


class ActionRequestSender:
    """The player's sender for one of an action's service event topics: its requests go to the action server."""

    def __init__(self, replay: ActionGoalReplay, connection: Connection) -> None:
        self.connection = connection
        self._replay = replay
        self._interface = action_interface(connection.topic) or ""
        self._event_class = message_class(connection.msgtype)
        self.published = 0

    def wants_object(self) -> bool:
        return False  # deserialized when due: only request events of one side are sent

    def make(self, data: bytes | memoryview) -> Any:
        return deserialize(data, self._event_class)

    def publish(self, data: bytes | memoryview, prepared: Any = None) -> bool:
        sent = self._replay.send(self._interface, self.make(data))
        self.published += sent
        return sent


def action_replays(node: Node, connections: list[Connection], source: str) -> dict[str, ActionGoalReplay]:
    """One replay per action whose type the bag tells (by its send_goal, get_result or feedback topic)."""
    replays: dict[str, ActionGoalReplay] = {}
    for connection in connections:
        if is_action_topic(connection.topic, connection.msgtype):
            name, type_name = action_name(connection.topic), action_type(connection.msgtype)
            if type_name is not None and name not in replays:
                replays[name] = ActionGoalReplay(node, name, type_name, source)
    return replays
