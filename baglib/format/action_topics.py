"""Action topics: how a recorded action looks in a bag (rosbag2 Kilted's ``rosbag2_cpp/action_utils``).

An action ``/fibonacci`` of type ``test_msgs/action/Fibonacci`` consists of two topics and three services; a bag
holds it as five topics (rosbag2's ``docs/design/rosbag2_record_replay_action.md``):

| interface   | topic                                          | type                                   |
|-------------|------------------------------------------------|----------------------------------------|
| send_goal   | ``/fibonacci/_action/send_goal/_service_event``   | ``test_msgs/action/Fibonacci_SendGoal_Event``  |
| cancel_goal | ``/fibonacci/_action/cancel_goal/_service_event`` | ``action_msgs/srv/CancelGoal_Event``           |
| get_result  | ``/fibonacci/_action/get_result/_service_event``  | ``test_msgs/action/Fibonacci_GetResult_Event`` |
| feedback    | ``/fibonacci/_action/feedback``                   | ``test_msgs/action/Fibonacci_FeedbackMessage`` |
| status      | ``/fibonacci/_action/status``                     | ``action_msgs/msg/GoalStatusArray``            |

A topic belongs to an action when both its name suffix and its type match one row; the service event topics
exist only where action introspection publishes them (Kilted's rcl_action, or the container's
:mod:`components.action_introspection` on Jazzy). Pure functions on names.
"""
from __future__ import annotations

import re
from collections.abc import Iterable

__all__ = [
    "INTERFACES",
    "SERVICE_INTERFACES",
    "action_interface",
    "action_name",
    "action_topics",
    "action_type",
    "actions_of",
    "is_action_topic",
]

#: interface name -> topic suffix after the action name (rosbag2's action_topic_to_postfix_map)
INTERFACES: dict[str, str] = {
    "send_goal": "/_action/send_goal/_service_event",
    "cancel_goal": "/_action/cancel_goal/_service_event",
    "get_result": "/_action/get_result/_service_event",
    "feedback": "/_action/feedback",
    "status": "/_action/status",
}
#: the interfaces that are services (their topics carry service events)
SERVICE_INTERFACES = ("send_goal", "cancel_goal", "get_result")

# rosbag2's action_topic_type_to_regex_map
_TYPES: dict[str, re.Pattern[str]] = {
    "send_goal": re.compile(r".+/action/.+_SendGoal_Event$"),
    "cancel_goal": re.compile(r"^action_msgs/srv/CancelGoal_Event$"),
    "get_result": re.compile(r".+/action/.+_GetResult_Event$"),
    "feedback": re.compile(r".+/action/.+_FeedbackMessage$"),
    "status": re.compile(r"^action_msgs/msg/GoalStatusArray$"),
}
# the suffix of the types that name the action's own type
_TYPE_SUFFIXES = {"send_goal": "_SendGoal_Event", "get_result": "_GetResult_Event", "feedback": "_FeedbackMessage"}


def action_interface(topic: str) -> str | None:
    """The interface (``send_goal`` ... ``status``) whose suffix ``topic`` ends with, after an action name."""
    for interface, suffix in INTERFACES.items():
        if len(topic) > len(suffix) and topic.endswith(suffix):
            return interface
    return None


def is_action_topic(topic: str, type_name: str) -> bool:
    """Whether ``topic`` of ``type_name`` is one of an action's five topics (rosbag2's
    ``is_topic_belong_to_action``): the name suffix and the type must both match."""
    interface = action_interface(topic)
    return interface is not None and bool(_TYPES[interface].search(type_name))


def action_name(topic: str) -> str:
    """``/fibonacci/_action/status`` -> ``/fibonacci``; ValueError for a topic of no action."""
    interface = action_interface(topic)
    if interface is None:
        raise ValueError(f"not an action topic (expected '<action>/_action/...'): {topic!r}")
    return topic[: -len(INTERFACES[interface])]


def action_type(type_name: str) -> str | None:
    """``pkg/action/Name_SendGoal_Event`` (or ``_GetResult_Event``, ``_FeedbackMessage``) -> ``pkg/action/Name``;
    None for the two types every action shares (CancelGoal_Event, GoalStatusArray) and for other types."""
    for interface, suffix in _TYPE_SUFFIXES.items():
        if _TYPES[interface].search(type_name):
            return type_name[: -len(suffix)]
    return None


def action_topics(name: str) -> dict[str, str]:
    """interface -> topic name for the action ``name`` (rosbag2's ``action_name_to_action_interface_names``).

    Raises:
        ValueError: ``name`` is empty or is itself an action topic (``/fib/_action/status`` names no action).
    """
    if not name.strip("/"):
        raise ValueError("an action name must not be empty")
    if "/_action/" in f"{name}/":
        raise ValueError(f"{name!r} is an action's topic, not an action name (expected e.g. "
                         f"{name.split('/_action')[0] or '/fibonacci'!r})")
    return {interface: name + suffix for interface, suffix in INTERFACES.items()}


def actions_of(topics: Iterable[tuple[str, str]]) -> dict[str, dict[str, str]]:
    """The actions among ``(topic, type)`` pairs: action name -> {interface: topic type}, in first-seen order."""
    actions: dict[str, dict[str, str]] = {}
    for topic, type_name in topics:
        if is_action_topic(topic, type_name):
            actions.setdefault(action_name(topic), {})[action_interface(topic) or ""] = type_name
    return actions
