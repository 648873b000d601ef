"""``events/messages_lost``: rosbag2 Rolling's live report of lost messages (rosbag2_interfaces/MessagesLostEvent).

Drops are counted per topic and reason anyway (``~/get_stats``); this publishes the change, so a monitoring
node learns about losses while they happen instead of at the end. As in rosbag2, an event is published only
when something was lost since the previous one, at most ``rate`` times a second, and topics without losses are
left out. "In transport" are messages that never reached the recorder's intake: lost by DDS (the
subscription's message-lost event), by an in-process queue, or by the container's image encoder before it
published them (a compressed topic's raw frames: RecordingSession.account_encoder); "in recorder" are the recorder's own drops
(cache full, unserializable, storage failure, received in the window but taken after its bag closed).

Each bag is reported on its own, from zero: its last changes (drops in the second before a stop, the messages a
slow writer was given up on) are published when it closes, before the next bag's first event.
"""
from __future__ import annotations

import threading
from collections import Counter
from typing import Any, Callable, Protocol

from rclpy.node import Node
from rosbag2_interfaces.msg import MessagesLostEvent, MessagesLostEventTopicStat

MESSAGES_LOST_TOPIC = "events/messages_lost"
#: An encoder's counts of raw frames it lost -> the drop reason of its output topic (RecordingSession).
ENCODER_LOSSES = {"skipped": "encoder_behind", "rejected": "encoder_rejected", "stopped": "encoder_stopped"}
#: Drop reasons (see RecordingSession) that happened before the recorder's intake.
TRANSPORT_REASONS = frozenset({"queue_full", *ENCODER_LOSSES.values()})


class Bag(Protocol):
    """A bag being recorded (RecordingSession), as far as loss events are concerned."""

    def drop_reasons(self) -> dict[str, dict[str, int]]:
        """Per topic, per reason: messages dropped so far."""


class LossEvents:
    """Publishes MessagesLostEvent on ``events/messages_lost`` when messages were lost; rate-limited."""

    def __init__(self, node: Node, current_bag: Callable[[], Bag | None], rate: float = 1.0) -> None:
        self._node = node
        self._current_bag = current_bag
        self._publisher = node.create_publisher(MessagesLostEvent, MESSAGES_LOST_TOPIC, 10)
        self._reported: dict[Bag, dict[str, tuple[int, int]]] = {}  # per bag, per topic: (transport, recorder)
        self._dds_lost: dict[Bag, Counter[str]] = {}  # per bag: the subscriptions' message-lost events
        # Held while a bag's counts are read and published: the timer and a closing bag never interleave.
        self._lock = threading.Lock()
        self._timer = node.create_timer(1.0 / rate, self.publish_changes)

    def dds_lost(self, topic: str, info: Any) -> None:
        """A subscription's message-lost event (rclpy QoSMessageLostInfo): counted for the bag being recorded."""
        bag = self._current_bag()
        if bag is not None:
            with self._lock:
                self._dds_lost.setdefault(bag, Counter())[topic] += info.total_count_change

    def publish_changes(self) -> None:
        """The timer: what the current bag lost since its previous event."""
        with self._lock:
            bag = self._current_bag()
            if bag is not None:
                self._publish(bag)

    def close_bag(self, bag: Bag) -> None:
        """``bag`` is closed: publish its last changes now, and forget it (the next bag starts from zero)."""
        with self._lock:
            self._publish(bag)
            self._reported.pop(bag, None)
            self._dds_lost.pop(bag, None)

    def _publish(self, bag: Bag) -> None:
        totals: dict[str, list[int]] = {}
        for topic, reasons in bag.drop_reasons().items():
            transport = sum(n for reason, n in reasons.items() if reason in TRANSPORT_REASONS)
            totals[topic] = [transport, sum(reasons.values()) - transport]
        for topic, count in self._dds_lost.get(bag, Counter()).items():
            totals.setdefault(topic, [0, 0])[0] += count
        reported = self._reported.setdefault(bag, {})
        event = MessagesLostEvent(node_name=self._node.get_fully_qualified_name())
        for topic, (transport, recorder) in sorted(totals.items()):
            before = reported.get(topic, (0, 0))
            if (transport, recorder) != before:
                event.messages_lost_statistics.append(MessagesLostEventTopicStat(
                    topic_name=topic, messages_lost_in_transport=max(0, transport - before[0]),
                    messages_lost_in_recorder=max(0, recorder - before[1])))
                reported[topic] = (transport, recorder)
        if event.messages_lost_statistics and self._node.context.ok():
            self._publisher.publish(event)
