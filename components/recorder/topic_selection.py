"""Which topics the recorder subscribes to, and with which QoS: rosbag2's TopicFilter and QoS adaptation.

Selection: ``all_topics``, or the explicit ``topics`` / ``topic_types`` / ``regex`` (any match selects),
minus ``exclude_topics`` / ``exclude_topic_types`` / ``exclude_regex``; hidden topics (a name part starting
with ``_``) only with ``include_hidden_topics``; topics without publishers only with
``include_unpublished_topics``. The recorder's own event topic is never recorded.

Service event topics (``<service>/_service_event`` of type ``pkg/srv/Name_Event``, see
:mod:`baglib.format.service_events`) are selected apart, as in rosbag2 Jazzy's TopicFilter: ``all_services``, or
the service named in ``services``, or ``regex`` matching the *service* name; minus ``exclude_services`` and
``exclude_regex`` (again on the service name). The topic options (``all_topics``, ``topics``,
``topic_types``, ``exclude_topics``, ``exclude_topic_types``, ``include_hidden_topics``) never apply to them,
although their names are hidden; ``include_unpublished_topics`` does.

QoS: reliable only if every publisher offers reliable, transient_local only if every publisher offers it,
keep_last with depth :data:`RECORDER_DEPTH`; an entry in the ``qos_profile_overrides_path`` YAML file replaces this.
"""
from __future__ import annotations

import re
from pathlib import Path

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from baglib.format.service_events import event_topic, is_service_event_topic, service_name
from components import qos_profiles
from components.recorder.recorder_options import RecordOptions

# rosbag2 uses 10. Here the subscription's queue is the only buffer between a publication and the intake
# callback, which runs on the container's (Python) executor: at 200 Hz, 10 messages are 50 ms, and a busy
# executor or a loaded machine stalls longer than that, losing messages long before the byte-bounded cache
# (max_cache_size) is anywhere near full. In-process the queue holds references to messages that exist anyway.
RECORDER_DEPTH = 100


class TopicFilter:
    """Decides per (topic, type) whether it is recorded."""

    def __init__(self, options: RecordOptions, own_topics: set[str]) -> None:
        self._options = options
        self._own_topics = own_topics
        self._regex = re.compile(options.regex) if options.regex else None
        self._exclude_regex = re.compile(options.exclude_regex) if options.exclude_regex else None
        self._topics = {qos_profiles.absolute_topic(t) for t in options.topics}
        self._exclude_topics = {qos_profiles.absolute_topic(t) for t in options.exclude_topics}
        # rosbag2 compares the event topic names the services map to
        self._services = {event_topic(qos_profiles.absolute_topic(s)) for s in options.services}
        self._exclude_services = {event_topic(qos_profiles.absolute_topic(s)) for s in options.exclude_services}

    def selects(self, topic: str, type_name: str, publisher_count: int) -> bool:
        o = self._options
        if topic in self._own_topics:
            return False
        if publisher_count == 0 and not o.include_unpublished_topics:
            return False
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



def _is_hidden(topic: str) -> bool:
    return any(part.startswith("_") for part in topic.split("/"))


def adapt_qos(offered: list[QoSProfile]) -> QoSProfile:
    """The subscription QoS that can receive from every offering publisher (rosbag2's rules)."""
    reliable = bool(offered) and all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    transient = bool(offered) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=RECORDER_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE)


def load_qos_overrides(parameter: str, path: Path | None) -> dict[str, QoSProfile]:
    """The recorder's ``record.qos_profile_overrides_path`` file (see qos_profiles.load_qos_overrides)."""
    return qos_profiles.load_qos_overrides(parameter, path, RECORDER_DEPTH)
