"""Which recorded topics the player publishes, with which QoS, and how one message goes out.

Selection is rosbag2_transport's ``allow_topic``: service event topics and ordinary topics have their own
include/exclude lists, the regexes apply to both; an action's five topics (rosbag2 Kilted) have theirs, by action
name, and the regexes see the action's name. QoS is rosbag2's ``publisher_qos_for_topic``: an override
file entry wins; otherwise, when every recorded publisher offered an effectively equal profile (reliability,
durability, deadline, liveliness and lease duration), that profile with the default history (keep_last 10);
otherwise rosbag2's default offer (reliable, volatile, keep_last 10).

A message goes out as what each kind of subscriber can use without waste: in-process subscribers of a
container get one message object (deserialized once, only if such a subscriber exists, big payloads without a
second copy: baglib.format.cdr_read), DDS readers get the recorded CDR bytes as they are.
"""
from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

from rclpy.node import Node
from rclpy.qos import QoSProfile

from baglib.format.cdr_read import deserialize
from baglib.read.reader import Connection
from baglib.format.action_topics import action_name, is_action_topic
from baglib.format.service_events import is_service_event_topic
from components.player.player_options import PlayOptions
from components.qos_profiles import profile_from_dict

#: rmw_qos_profile_default's depth: rosbag2's default_history() and its default offer.
DEFAULT_DEPTH = 10
_COMPATIBILITY = ("reliability", "durability", "deadline", "liveliness", "liveliness_lease_duration")


def allow_topic(connection: Connection, options: PlayOptions) -> bool:
    """rosbag2's ``allow_topic``: excludes first, then the include list (or the regex) if any is set."""
    if is_action_topic(connection.topic, connection.msgtype):
        name, exclude, include = action_name(connection.topic), options.exclude_actions, options.actions
    elif is_service_event_topic(connection.topic, connection.msgtype):
        name, exclude, include = connection.topic, options.exclude_services, options.services
    else:
        name, exclude, include = connection.topic, options.exclude_topics, options.topics
    if name in exclude:
        return False
    if options.exclude_regex and re.fullmatch(options.exclude_regex, name):
        return False
    if not include and not options.regex:
        return True
    if name in include:
        return True
    return bool(options.regex) and re.fullmatch(options.regex, name) is not None


def publisher_qos(connection: Connection, overrides: dict[str, QoSProfile], warn: Callable[[str], None]
                  ) -> QoSProfile:
    """The QoS the player offers on ``connection.topic`` (rosbag2's ``adapt_offer_to_recorded_offers``)."""
    if connection.topic in overrides:
        return overrides[connection.topic]
    offered = connection.offered_qos_profiles
    if not offered:
        return QoSProfile(depth=DEFAULT_DEPTH)
    first = offered[0]
    if all(all(p.get(key) == first.get(key) for key in _COMPATIBILITY) for p in offered[1:]):
        profile = {k: v for k, v in first.items() if k not in ("history", "depth")}
        try:
            return profile_from_dict({**profile, "history": "keep_last", "depth": DEFAULT_DEPTH}, DEFAULT_DEPTH)
        except (ValueError, TypeError, KeyError, AttributeError, OverflowError):
            warn(f"The recorded QoS of {connection.topic} cannot be used here: offering rosbag2's default")
            return QoSProfile(depth=DEFAULT_DEPTH)
    warn(f"Not all original publishers on topic {connection.topic} offered the same QoS profiles. "
         "Falling back to the rosbag2_storage default publisher offer.")
    return QoSProfile(depth=DEFAULT_DEPTH)


class TopicPublisher:
    """One recorded topic's publisher in the player node."""

    def __init__(self, node: Node, connection: Connection, msg_class: type, qos: QoSProfile) -> None:
        self.connection = connection
        self.msg_class = msg_class
        self.publisher = node.create_publisher(msg_class, connection.topic, qos)
        #: in a container with intra-process comms: IntraProcessPublisher.publish_recorded
        self._publish_recorded = getattr(self.publisher, "publish_recorded", None)
        self.published = 0

    def wants_object(self) -> bool:
        """Whether an in-process subscriber exists now (the read-ahead then deserializes ahead of time)."""
        return self._publish_recorded is not None and self.publisher.local_subscription_count() > 0

    def make(self, data: bytes | memoryview) -> Any:
        return deserialize(data, self.msg_class)

    def publish(self, data: bytes | memoryview, prepared: Any = None) -> bool:
        """Publish one recorded message; ``prepared`` is its object if the read-ahead already made it."""
        if self._publish_recorded is None:
            self.publisher.publish(data if isinstance(data, bytes) else bytes(data))
        else:
            self._publish_recorded(data, (lambda: prepared) if prepared is not None else (lambda: self.make(data)))
        self.published += 1
        return True
