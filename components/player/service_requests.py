"""``play.publish_service_request``: recorded service requests sent to the live service, as rosbag2 does.

Instead of publishing a service's recorded events, the player calls the service with each recorded request:
the events the service received (``SERVICE_INTROSPECTION``, the default) or the ones clients sent
(``CLIENT_INTROSPECTION``). Responses and the other side's events are skipped, as are requests recorded with
metadata-only introspection (one warning) and requests while the service is not available (an error each,
as rosbag2_transport's PlayerImpl::publish_message).
"""
from __future__ import annotations

import importlib
from typing import Any

from rclpy.node import Node
from service_msgs.msg import ServiceEventInfo

from baglib.format.cdr_read import deserialize
from baglib.read.reader import Connection
from baglib.format.service_events import event_class, service_name, service_type

#: play.service_requests_source -> the event type it sends
REQUEST_EVENTS = {"SERVICE_INTROSPECTION": ServiceEventInfo.REQUEST_RECEIVED,
                  "CLIENT_INTROSPECTION": ServiceEventInfo.REQUEST_SENT}


def service_class(event_type_name: str) -> Any:
    package, _, name = service_type(event_type_name).split("/")
    return getattr(importlib.import_module(f"{package}.srv"), name)


class ServiceRequestSender:
    """One recorded service's client: the player's sender for that service's event topic."""

    def __init__(self, node: Node, connection: Connection, source: str) -> None:
        self.connection = connection
        self.service = service_name(connection.topic)
        self._event_class = event_class(connection.msgtype)
        self.client = node.create_client(service_class(connection.msgtype), self.service)
        self._wanted = REQUEST_EVENTS[source]
        self._logger = node.get_logger()
        self._warned_metadata_only = False
        self.published = 0

    def wants_object(self) -> bool:
        return False  # the event is deserialized when it is due: only request events of one side are sent

    def make(self, data: bytes | memoryview) -> Any:
        return deserialize(data, self._event_class)

    def publish(self, data: bytes | memoryview, prepared: Any = None) -> bool:
        """Send the request this event carries; False when it is not one to send (see module docstring)."""
        event = self.make(data)
        if event.info.event_type != self._wanted:
            return False
        if not self.client.service_is_ready():
            self._logger.error(f"Service request hasn't been sent. The '{self.service}' service isn't ready !")
            return False
        if not event.request:
            if not self._warned_metadata_only:
                self._warned_metadata_only = True
                self._logger.warning(f"Can't send service request. The configuration of introspection for "
                                     f"'{self.service}' was metadata only!")
            return False
        self.client.call_async(event.request[0])
        self.published += 1
        return True
