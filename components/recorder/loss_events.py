"""``events/messages_lost``: rosbag2 Rolling's live report of lost messages (rosbag2_interfaces/MessagesLostEvent).

Drops are counted per topic and reason anyway (``~/get_stats``); this publishes the change, so a monitoring
node learns about losses while they happen instead of at the end. As in rosbag2, an event is published only
when something was lost since the previous one, at most ``rate`` times a second, and topics without losses are
left out. "In transport" are messages that never reached the recorder's intake: lost by DDS (the
subscription's message-lost event) or by an in-process queue; "in recorder" are the recorder's own drops
(cache full, unserializable, storage failure, arrived after the recording stopped).
"""
from __future__ import annotations

import threading
from collections import Counter
from typing import Any, Callable

from rclpy.node import Node
from rosbag2_interfaces.msg import MessagesLostEvent, MessagesLostEventTopicStat

MESSAGES_LOST_TOPIC = "events/messages_lost"
#: Drop reasons (see RecordingSession) that happened before the recorder's intake.
TRANSPORT_REASONS = frozenset({"queue_full"})

#: per topic, per reason: messages dropped so far (RecordingSession.stats()["drop_reasons"])
DropCounts = Callable[[], dict[str, dict[str, int]]]


class LossEvents:
    """Publishes MessagesLostEvent on ``events/messages_lost`` when messages were lost; rate-limited."""

    def __init__(self, node: Node, drops: DropCounts, rate: float = 1.0) -> None:
        self._node = node
        self._drops = drops
        self._publisher = node.create_publisher(MessagesLostEvent, MESSAGES_LOST_TOPIC, 10)
        self._reported: dict[str, tuple[int, int]] = {}  # per topic: (transport, recorder) already published
        self._dds_lost: Counter[str] = Counter()  # from the subscriptions' message-lost events
        self._lock = threading.Lock()
        self._timer = node.create_timer(1.0 / rate, self.publish_changes)

    def dds_lost(self, topic: str, info: Any) -> None:
        """A subscription's message-lost event (rclpy QoSMessageLostInfo)."""
        with self._lock:
            self._dds_lost[topic] += info.total_count_change

    def reset(self) -> None:
        """A new bag: its drop counts start from zero."""
        self._reported.clear()

    def publish_changes(self) -> None:
        totals: dict[str, list[int]] = {}
        for topic, reasons in self._drops().items():
            transport = sum(n for reason, n in reasons.items() if reason in TRANSPORT_REASONS)
            totals[topic] = [transport, sum(reasons.values()) - transport]
        with self._lock:
            for topic, count in self._dds_lost.items():
                totals.setdefault(topic, [0, 0])[0] += count
        event = MessagesLostEvent(node_name=self._node.get_fully_qualified_name())
        for topic, (transport, recorder) in sorted(totals.items()):
            before = self._reported.get(topic, (0, 0))
            if (transport, recorder) != before:
                event.messages_lost_statistics.append(MessagesLostEventTopicStat(
                    topic_name=topic, messages_lost_in_transport=max(0, transport - before[0]),
                    messages_lost_in_recorder=max(0, recorder - before[1])))
                self._reported[topic] = (transport, recorder)
        if event.messages_lost_statistics:
            self._publisher.publish(event)
