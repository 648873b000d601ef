"""Service events: how a recorded service looks in a bag (rosbag2 Jazzy's ``rosbag2_cpp/service_utils``).

A service server or client with introspection enabled publishes every request and response it sends or
receives on the topic ``<service>/_service_event``, typed ``<pkg>/srv/<Name>_Event`` (rosidl generates one
such message per service: ``service_msgs/msg/ServiceEventInfo info``, ``<Name>_Request[<=1] request``,
``<Name>_Response[<=1] response``). A bag stores these topics like any other; the names below are how
recorder, player and ``bag info`` tell them apart and map them back to the service.

Pure functions on names, plus :func:`event_class` (an import, no node) and :func:`event_info` (the
``ServiceEventInfo`` at the start of every event's CDR, whatever the service).
"""
from __future__ import annotations

import importlib
import re
import struct
from typing import Any

__all__ = [
    "EVENT_TOPIC_SUFFIX",
    "EVENT_TYPE_SUFFIX",
    "event_class",
    "event_info",
    "event_topic",
    "event_type",
    "is_service_event_topic",
    "service_name",
    "service_type",
]

#: rcl's RCL_SERVICE_INTROSPECTION_TOPIC_POSTFIX
EVENT_TOPIC_SUFFIX = "/_service_event"
#: rosidl's SERVICE_EVENT_MESSAGE_SUFFIX
EVENT_TYPE_SUFFIX = "_Event"

#: ServiceEventInfo.event_type values (service_msgs): requests sent/received, responses sent/received
REQUEST_EVENTS = (0, 1)
RESPONSE_EVENTS = (2, 3)
# After the 4-byte encapsulation header: event_type uint8 @0, stamp (int32, uint32) @4, client_gid uint8[16]
# @12, sequence_number int64 @32 (aligned to 8).
_INFO = {endian: struct.Struct(f"{endian}B11x16s4xq") for endian in "<>"}

_SERVICE_TYPE = re.compile(r"^([a-zA-Z][a-zA-Z0-9_]*)/srv/([a-zA-Z][a-zA-Z0-9_]*)$")


def is_service_event_topic(topic: str, type_name: str) -> bool:
    """Whether ``topic`` of ``type_name`` carries service events (rosbag2's ``is_service_event_topic``).

    Both must hold: the name ends in ``/_service_event`` (with a service name before it) and the type is
    ``<pkg>/srv/<Name>_Event``. A topic meeting only one of them is an ordinary topic.
    """
    return (len(topic) > len(EVENT_TOPIC_SUFFIX) and topic.endswith(EVENT_TOPIC_SUFFIX)
            and "/srv/" in type_name and len(type_name) > len(EVENT_TYPE_SUFFIX)
            and type_name.endswith(EVENT_TYPE_SUFFIX))


def service_name(topic: str) -> str:
    """``/add_two_ints/_service_event`` -> ``/add_two_ints``; ValueError for any other topic name."""
    if len(topic) <= len(EVENT_TOPIC_SUFFIX) or not topic.endswith(EVENT_TOPIC_SUFFIX):
        raise ValueError(f"not a service event topic (expected '<service>{EVENT_TOPIC_SUFFIX}'): {topic!r}")
    return topic[: -len(EVENT_TOPIC_SUFFIX)]


def event_topic(service: str) -> str:
    """``/add_two_ints`` -> ``/add_two_ints/_service_event``; an event topic name is returned unchanged.

    Like rosbag2's ``service_name_to_service_event_topic_name``, which lets ``record.services`` name either.
    The name is not made absolute: relative names stay relative.
    """
    if not service:
        raise ValueError("a service name must not be empty")
    if len(service) > len(EVENT_TOPIC_SUFFIX) and service.endswith(EVENT_TOPIC_SUFFIX):
        return service
    return service + EVENT_TOPIC_SUFFIX


def service_type(event_type_name: str) -> str:
    """``example_interfaces/srv/AddTwoInts_Event`` -> ``example_interfaces/srv/AddTwoInts``; else ValueError."""
    if event_type_name.endswith(EVENT_TYPE_SUFFIX):
        candidate = event_type_name[: -len(EVENT_TYPE_SUFFIX)]
        if _SERVICE_TYPE.match(candidate):
            return candidate
    raise ValueError(f"not a service event type (expected 'pkg/srv/Name{EVENT_TYPE_SUFFIX}'): {event_type_name!r}")


def event_type(service_type_name: str) -> str:
    """``example_interfaces/srv/AddTwoInts`` -> ``example_interfaces/srv/AddTwoInts_Event``; else ValueError."""
    if not _SERVICE_TYPE.match(service_type_name):
        raise ValueError(f"not a service type (expected 'pkg/srv/Name'): {service_type_name!r}")
    return service_type_name + EVENT_TYPE_SUFFIX


def event_class(event_type_name: str) -> Any:
    """The Python class of ``pkg/srv/Name_Event`` (``pkg.srv.Name.Event``).

    Raises ValueError for a name that is not an event type, ImportError / AttributeError when the service's
    package or type is not installed.
    """
    package, _, name = service_type(event_type_name).split("/")
    return getattr(importlib.import_module(f"{package}.srv"), name).Event


def event_info(data: bytes | memoryview) -> tuple[int, bytes, int]:
    """(event_type, client_gid, sequence_number) of a serialized service event; ValueError if it is too short."""
    if len(data) < 4 + _INFO["<"].size:
        raise ValueError(f"a service event of {len(data)} bytes is too short for its ServiceEventInfo")
    endian = "<" if data[1] & 1 else ">"  # CDR_LE / CDR_BE (encapsulation kind 1 / 0)
    return _INFO[endian].unpack_from(data, 4)
