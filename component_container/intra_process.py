"""The intra-process path: zero-copy delivery of message objects between nodes of one container.

rclpy has no intra-process transport; this module is it. Publishers and subscriptions of components that opt
in register here by topic. ``publish(msg)`` appends the very object to the bounded queue of every compatible
in-process subscription and triggers that subscription's guard condition, so the callback runs on the
container's executor with the object the publisher built: no serialization, no copy, no C conversion.

DDS still carries the topic for everyone else: a publisher writes to DDS only while out-of-process (or
non-intra-process) subscribers are matched, and an in-process subscription keeps a DDS reader for publishers
outside the container. When a local publisher also writes to DDS, the local subscriptions' DDS readers get
that sample too; it is recognised (writer sequence number and source timestamp recorded at write time, see
:class:`LocalPublicationLog`) and dropped, so no in-process subscriber sees a message twice.

Ownership rule: after ``publish()`` the message belongs to the subscribers; the publisher must not mutate it.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# How many recent DDS writes of a volatile publisher stay recognisable to the local DDS readers.
PUBLICATION_LOG_DEPTH = 256


def qos_compatible(offered: QoSProfile, requested: QoSProfile) -> bool:
    """DDS request/offer rules for the policies that matter in-process."""
    if (requested.reliability == ReliabilityPolicy.RELIABLE
            and offered.reliability == ReliabilityPolicy.BEST_EFFORT):
        return False
    if (requested.durability == DurabilityPolicy.TRANSIENT_LOCAL
            and offered.durability == DurabilityPolicy.VOLATILE):
        return False
    return True


class LocalPublicationLog:
    """Recent DDS writes of one local publisher: writer sequence number -> (time before, time after).

    Fast DDS numbers a writer's samples 1, 2, 3... and stamps each with the source time of the write, and
    both reach the subscriber in its message info. A sample whose sequence number this publisher used and
    whose source timestamp lies inside the window around that write came from this publisher.
    """

    def __init__(self, depth: int) -> None:
        self._writes: dict[int, tuple[int, int]] = {}
        self._order: deque[int] = deque()
        self._depth = max(depth, PUBLICATION_LOG_DEPTH)
        self._next_sequence = 1
        self._lock = threading.Lock()

    def record(self, write: Callable[[], None]) -> None:
        """Perform one DDS write and remember its sequence number and time window."""
        with self._lock:  # serialises writes so the sequence number we record is the one DDS assigns
            before = time.time_ns()
            write()
            after = time.time_ns()
            sequence = self._next_sequence
            self._next_sequence += 1
            self._writes[sequence] = (before, after)
            self._order.append(sequence)
            if len(self._order) > self._depth:
                del self._writes[self._order.popleft()]

    def contains(self, sequence: int, source_timestamp: int) -> bool:
        window = self._writes.get(sequence)
        return window is not None and window[0] <= source_timestamp <= window[1]


@dataclass(eq=False)
class IntraProcessSubscription:
    """An in-process subscription: its bounded queue, drop counter and the hook that wakes its executor.

    With ``inline`` set there is no queue: ``offer`` calls it at once, in the publisher's thread (see
    ``ComponentNode.create_subscription(intra_process_inline=True)``).
    """

    topic: str
    qos: QoSProfile
    wake: Callable[[], None]
    inline: Callable[[Any, tuple[int, int]], None] | None = None
    queue: deque = field(default_factory=deque)
    received: int = 0
    dropped: int = 0

    def __post_init__(self) -> None:
        keep_last = self.qos.history != HistoryPolicy.KEEP_ALL
        self.queue = deque(maxlen=max(self.qos.depth, 1) if keep_last else None)
        self._lock = threading.Lock()

    def offer(self, message: Any, stamps: tuple[int, int]) -> None:
        """Queue a message (dropping the oldest if keep_last is full) and wake the executor."""
        if self.inline is not None:
            with self._lock:
                self.received += 1
            self.inline(message, stamps)
            return
        with self._lock:
            if self.queue.maxlen is not None and len(self.queue) == self.queue.maxlen:
                self.dropped += 1
            self.queue.append((message, stamps))
            self.received += 1
        self.wake()

    def take(self) -> tuple[Any, tuple[int, int]] | None:
        """The oldest queued message with its (publish, receive) nanosecond stamps, or None."""
        with self._lock:
            return self.queue.popleft() if self.queue else None


@dataclass(eq=False)
class IntraProcessPublication:
    """A local publisher's registration: its QoS, its DDS write log and, if transient_local, its history."""

    topic: str
    qos: QoSProfile
    log: LocalPublicationLog
    history: deque | None


class IntraProcessManager:
    """The container-wide registry that routes published objects to in-process subscriptions."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subscriptions: dict[str, list[IntraProcessSubscription]] = {}
        self._publications: dict[str, list[IntraProcessPublication]] = {}

    def add_publication(self, topic: str, qos: QoSProfile) -> IntraProcessPublication:
        transient = qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        publication = IntraProcessPublication(topic, qos, LocalPublicationLog(qos.depth),
                                              deque(maxlen=max(qos.depth, 1)) if transient else None)
        with self._lock:
            self._publications.setdefault(topic, []).append(publication)
        return publication

    def add_subscription(self, subscription: IntraProcessSubscription) -> None:
        """Register a subscription; transient_local publishers hand it their stored messages at once."""
        with self._lock:
            self._subscriptions.setdefault(subscription.topic, []).append(subscription)
            late = [(message, stamps) for p in self._publications.get(subscription.topic, [])
                    if p.history is not None and qos_compatible(p.qos, subscription.qos)
                    for message, stamps in p.history]
        for message, stamps in sorted(late, key=lambda item: item[1][0]):
            subscription.offer(message, stamps)

    def remove_publication(self, publication: IntraProcessPublication) -> None:
        with self._lock:
            _remove(self._publications, publication.topic, publication)

    def remove_subscription(self, subscription: IntraProcessSubscription) -> None:
        with self._lock:
            _remove(self._subscriptions, subscription.topic, subscription)

    def subscriptions_for(self, publication: IntraProcessPublication) -> list[IntraProcessSubscription]:
        """The in-process subscriptions that may receive from this publication (QoS-compatible)."""
        with self._lock:
            candidates = list(self._subscriptions.get(publication.topic, ()))
        return [s for s in candidates if qos_compatible(publication.qos, s.qos)]

    def deliver(self, publication: IntraProcessPublication, message: Any) -> int:
        """Hand ``message`` to every compatible in-process subscription; returns how many got it."""
        now = time.time_ns()
        stamps = (now, now)
        if publication.history is not None:
            publication.history.append((message, stamps))
        targets = self.subscriptions_for(publication)
        for subscription in targets:
            subscription.offer(message, stamps)
        return len(targets)

    def is_local_publication(self, topic: str, sequence: int | None, source_timestamp: int) -> bool:
        """Whether a DDS sample on ``topic`` was written by a publisher in this container."""
        if sequence is None:
            return False
        with self._lock:
            publications = list(self._publications.get(topic, ()))
        return any(p.log.contains(sequence, source_timestamp) for p in publications)


def _remove(registry: dict[str, list], topic: str, entry: object) -> None:
    entries = registry.get(topic, [])
    if entry in entries:
        entries.remove(entry)
    if not entries:
        registry.pop(topic, None)
