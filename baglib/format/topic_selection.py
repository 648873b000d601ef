"""rosbag2's topic selection (``TopicFilter`` of rosbag2_transport, Jazzy) on names and types alone: which topics a
set of record options takes. The recorder adds what only a live graph knows (its own topics, publishers); ``bag
convert`` applies it to the topics of its input bags, as rosbag2's ``bag_rewrite`` does.

Topics: ``all_topics``, or the explicit ``topics`` / ``topic_types`` / ``regex`` (any match selects), minus
``exclude_topics`` / ``exclude_topic_types`` / ``exclude_regex``; hidden topics (a name part starting with ``_``)
only with ``include_hidden_topics`` or when named in ``topics``.

Service event topics (``<service>/_service_event`` of type ``pkg/srv/Name_Event``, see
:mod:`baglib.format.service_events`) are selected apart: ``all_services``, or the service named in ``services``,
or ``regex`` matching the *service* name; minus ``exclude_services`` and ``exclude_regex`` (again on the service
name). The topic options never apply to them, although their names are hidden.

An action's five topics (see :mod:`baglib.format.action_topics`; rosbag2 Kilted) are selected apart again, before
the service rule (its ``cancel_goal`` events are typed ``action_msgs/srv/CancelGoal_Event``): ``all_actions``, or
the action named in ``actions``, or ``regex`` matching the *action* name; minus ``exclude_actions`` and
``exclude_regex`` (on the action name). Neither the topic nor the service options take them.

Names in the lists may leave out the leading ``/``.
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Protocol

from baglib.format.action_topics import action_name, action_topics, is_action_topic
from baglib.format.service_events import event_topic, is_service_event_topic, service_name

__all__ = ["SelectionOptions", "TopicSelection", "absolute_name"]


class SelectionOptions(Protocol):
    """The record options a selection reads (rosbag2's ``RecordOptions`` names)."""

    all_topics: bool
    all_services: bool
    topics: Sequence[str]
    topic_types: Sequence[str]
    services: Sequence[str]
    exclude_topics: Sequence[str]
    exclude_topic_types: Sequence[str]
    exclude_services: Sequence[str]
    all_actions: bool
    actions: Sequence[str]
    exclude_actions: Sequence[str]
    regex: str
    exclude_regex: str
    include_hidden_topics: bool


def absolute_name(name: str) -> str:
    """``name`` with its leading ``/``."""
    return name if name.startswith("/") else f"/{name}"


class TopicSelection:
    """Decides per (topic, type) whether the options take it (see module doc).

    Raises:
        re.error: ``regex`` or ``exclude_regex`` is not a regular expression.
        ValueError: a name in ``actions`` / ``exclude_actions`` is no action name (see ``action_topics``).
    """

    def __init__(self, options: SelectionOptions) -> None:
        self._options = options
        self._regex = re.compile(options.regex) if options.regex else None
        self._exclude_regex = re.compile(options.exclude_regex) if options.exclude_regex else None
        self._topics = {absolute_name(topic) for topic in options.topics}
        self._exclude_topics = {absolute_name(topic) for topic in options.exclude_topics}
        # rosbag2 compares the event topic names the services map to
        self._services = {event_topic(absolute_name(service)) for service in options.services}
        self._exclude_services = {event_topic(absolute_name(service)) for service in options.exclude_services}
        self._actions = _action_names(options.actions)
        self._exclude_actions = _action_names(options.exclude_actions)

    def selects(self, topic: str, type_name: str) -> bool:
        o = self._options
        topic = absolute_name(topic)
        if is_action_topic(topic, type_name):
            return self._selects_action(action_name(topic))
        if is_service_event_topic(topic, type_name):
            return self._selects_service(topic)
        explicitly_named = topic in self._topics
        if _is_hidden(topic) and not (o.include_hidden_topics or explicitly_named):
            return False
        wanted = (o.all_topics or explicitly_named or type_name in o.topic_types
                  or bool(self._regex and self._regex.search(topic)))
        if not wanted:
            return False
        if topic in self._exclude_topics or type_name in o.exclude_topic_types:
            return False
        return not (self._exclude_regex and self._exclude_regex.search(topic))

    def _selects_service(self, topic: str) -> bool:
        """The service options for a service event topic; the regexes see the service's name."""
        service = service_name(topic)
        wanted = (self._options.all_services or topic in self._services
                  or bool(self._regex and self._regex.search(service)))
        if not wanted or topic in self._exclude_services:
            return False
        return not (self._exclude_regex and self._exclude_regex.search(service))

    def _selects_action(self, action: str) -> bool:
        """The action options for one of an action's topics; the regexes see the action's name."""
        wanted = (self._options.all_actions or action in self._actions
                  or bool(self._regex and self._regex.search(action)))
        if not wanted or action in self._exclude_actions:
            return False
        return not (self._exclude_regex and self._exclude_regex.search(action))


def _action_names(names: Sequence[str]) -> set[str]:
    """The absolute action names; ValueError (from ``action_topics``) for a name that is no action's."""
    absolute = {absolute_name(name) for name in names}
    for name in absolute:
        action_topics(name)
    return absolute


def _is_hidden(topic: str) -> bool:
    return any(part.startswith("_") for part in topic.split("/"))
