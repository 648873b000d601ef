"""The intra-process path: zero-copy delivery of message objects between nodes of one container.

rclpy has no intra-process transport; this module is it. Publishers and subscriptions of components that opt
in register here by topic. ``publish(msg)`` appends the very object to the bounded queue of every compatible
in-process subscription and wakes that subscription's executor (a :class:`Wakeup`: a guard condition of the
subscriber's node for the wait-set executors, a task posted to rclpy's EventsExecutor, which has no guard
conditions), so the callback runs on the container's executor with the object the publisher built: no
serialization, no copy, no C conversion.

DDS still carries the topic for everyone else: a publisher writes to DDS only while out-of-process (or
non-intra-process) subscribers are matched, and an in-process subscription keeps a DDS reader for publishers
outside the container. When a local publisher also writes to DDS, the local subscriptions' DDS readers get
that sample too; it is recognised (writer sequence number and source timestamp recorded at write time, see
:class:`LocalPublicationLog`) and dropped, so no in-process subscriber sees a message twice.

A transient_local publisher keeps its last ``depth`` delivered messages; a transient_local subscription that
joins later gets them once, in publish order, before any later message of that publisher (see
:meth:`IntraProcessManager.add_subscription`). Its DDS reader gets the same samples from the DDS history and
drops them as local ones.

Ownership rule: after ``publish()`` the message belongs to the subscribers; the publisher must not mutate it.
"""
from __future__ import annotations

import contextlib
import heapq
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

from rclpy.callback_groups import CallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from component_container.callback_supervision import COMPONENT_ERRORS

# How many recent DDS writes of a volatile publisher stay recognisable to the local DDS readers.
PUBLICATION_LOG_DEPTH = 256
# keep_all in-process queues are bounded like a middleware reader's resource limits (Fast DDS bounds keep_all
# readers too): past either limit a new message is refused and counted in ``dropped``, so a stalled subscriber
# of 1080p frames costs at most this much memory instead of growing until the process is killed.
KEEP_ALL_MAX_MESSAGES = 1000
KEEP_ALL_MAX_BYTES = 256 * 1024 * 1024
# How many destroyed publishers' logs a topic keeps, so that their last DDS samples, still queued in local readers
# when the publisher was unloaded, are recognised too (kept while the topic has in-process subscriptions).
RETIRED_LOGS_PER_TOPIC = 8
# How long closing a subscription waits for its inline callbacks (which must never block) to return.
INLINE_DRAIN_TIMEOUT = 1.0


class Wakeup(Protocol):
    """Makes the executor that runs a node call one callback of it soon, from any thread."""

    def trigger(self) -> None:
        """Ask for one call (triggers before that call coalesce into it)."""

    def destroy(self) -> None:
        """No more calls: the subscription is going away."""


#: ``make_wakeup(node, callback, callback_group)``: what each executor model provides (component_executors).
WakeupFactory = Callable[[Node, Callable[[], None], CallbackGroup | None], Wakeup]


class GuardConditionWakeup:
    """A wait-set executor's wake-up: a guard condition of the node, with ``callback`` as its callback."""

    def __init__(self, node: Node, callback: Callable[[], None], group: CallbackGroup | None) -> None:
        self._node = node
        self._guard = node.create_guard_condition(callback, group)

    def trigger(self) -> None:
        self._guard.trigger()

    def destroy(self) -> None:
        self._node.destroy_guard_condition(self._guard)


def qos_compatible(offered: QoSProfile, requested: QoSProfile) -> bool:
    """DDS request/offer rules for the policies that matter in-process."""
    if (requested.reliability == ReliabilityPolicy.RELIABLE
            and offered.reliability == ReliabilityPolicy.BEST_EFFORT):
        return False
    if (requested.durability == DurabilityPolicy.TRANSIENT_LOCAL
            and offered.durability == DurabilityPolicy.VOLATILE):
        return False
    return True


#: The end of the time window of a write still in progress: any source timestamp after its start matches.
_WRITING = 2**63 - 1


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
        """Perform one DDS write and remember its sequence number and time window.

        The entry is made before the write, open-ended, and closed after it: a reader of this process may take
        the sample while ``write`` is still running (another executor thread), and must already know it as
        this publisher's, or the subscriber would get the message a second time, over DDS.
        """
        with self._lock:  # serialises writes so the sequence number we record is the one DDS assigns
            sequence = self._next_sequence
            before = time.time_ns()
            self._writes[sequence] = (before, _WRITING)
            self._order.append(sequence)
            if len(self._order) > self._depth:
                del self._writes[self._order.popleft()]
            try:
                write()
            except BaseException:
                del self._writes[sequence]
                self._order.pop()
                raise
            self._writes[sequence] = (before, time.time_ns())
            self._next_sequence += 1

    def contains(self, sequence: int, source_timestamp: int) -> bool:
        window = self._writes.get(sequence)
        return window is not None and window[0] <= source_timestamp <= window[1]


@dataclass(eq=False)
class IntraProcessSubscription:
    """An in-process subscription: its bounded queue, drop counter and the hook that wakes its executor.

    With ``inline`` set there is no queue: ``offer`` calls it at once, in the publisher's thread (see
    ``ComponentNode.create_subscription(intra_process_inline=True)``); what it raises goes to ``on_error``,
    never into the publisher. After :meth:`close` (the subscriber is being destroyed) offers are ignored, so a
    publish racing with an unload never touches the subscriber's destroyed guard condition.
    """

    topic: str
    qos: QoSProfile
    wake: Callable[[], None]
    inline: Callable[[Any, tuple[int, int]], None] | None = None
    on_error: Callable[[BaseException], None] | None = None
    queue: deque = field(default_factory=deque)
    received: int = 0
    dropped: int = 0

    def __post_init__(self) -> None:
        self._keep_all = self.qos.history == HistoryPolicy.KEEP_ALL
        self.queue = deque(maxlen=None if self._keep_all else max(self.qos.depth, 1))
        self._queued_bytes = 0
        self._closed = False
        self._inline_running = 0
        # The hot paths take the bare lock (a C-level context manager); close() waits on the condition over it.
        self._mutex = threading.Lock()
        self._lock = threading.Condition(self._mutex)

    def offer(self, message: Any, stamps: tuple[int, int]) -> None:
        """Queue a message (keep_last: dropping the oldest; keep_all: refusing it past the limits) and wake
        the executor; inline subscriptions run their callback here instead."""
        if self.inline is not None:
            self._offer_inline(message, stamps)
            return
        with self._mutex:
            if self._closed:
                return
            self.received += 1
            if self._keep_all:
                size = rough_size(message)
                if len(self.queue) >= KEEP_ALL_MAX_MESSAGES or self._queued_bytes + size > KEEP_ALL_MAX_BYTES:
                    self.dropped += 1  # like a middleware reader at its resource limits: the sample is refused
                    return
                self._queued_bytes += size
            elif len(self.queue) == self.queue.maxlen:
                self.dropped += 1
            self.queue.append((message, stamps))
            self.wake()  # under the lock: close() cannot destroy the wake-up in between

    def _offer_inline(self, message: Any, stamps: tuple[int, int]) -> None:
        with self._mutex:
            if self._closed:
                return
            self.received += 1
            self._inline_running += 1
        try:
            self.inline(message, stamps)  # type: ignore[misc]  # checked by the caller
        except COMPONENT_ERRORS as exc:
            if self.on_error is None:
                raise
            self.on_error(exc)
        finally:
            with self._mutex:
                self._inline_running -= 1
                if self._closed:  # close() may be waiting for this callback
                    self._lock.notify_all()

    def take(self) -> tuple[Any, tuple[int, int]] | None:
        """The oldest queued message with its (publish, receive) nanosecond stamps, or None."""
        with self._mutex:
            if not self.queue:
                return None
            item = self.queue.popleft()
            if self._keep_all:
                self._queued_bytes -= rough_size(item[0])
            return item

    def close(self, timeout: float = INLINE_DRAIN_TIMEOUT) -> None:
        """Accept nothing more and wait (bounded) for inline callbacks running in publishers' threads."""
        with self._lock:
            self._closed = True
            self.queue.clear()
            self._lock.wait_for(lambda: self._inline_running == 0, timeout)


def rough_size(message: Any) -> int:
    """A cheap estimate of a message's bytes for the keep_all byte limit: its ``data`` buffer plus headers."""
    data = getattr(message, "data", None)
    return 256 + (len(data) if hasattr(data, "__len__") else 0)


def is_transient_local(qos: QoSProfile) -> bool:
    return qos.durability == DurabilityPolicy.TRANSIENT_LOCAL


def kept_messages(qos: QoSProfile) -> int:
    """How many messages a transient_local endpoint keeps: its depth, or a keep_all reader's message limit."""
    return KEEP_ALL_MAX_MESSAGES if qos.history == HistoryPolicy.KEEP_ALL else max(qos.depth, 1)


@dataclass(eq=False)
class IntraProcessPublication:
    """A local publisher's registration: its QoS, its DDS write log and, if transient_local, its history.

    ``history`` holds ``(message, publish time)`` of the last delivered messages, the very objects the
    subscribers got (so the reuse rule covers them as it covers theirs); it goes with the publication when
    the publisher is destroyed, as a DDS writer's history does. ``lock`` (transient_local only) makes keeping
    and handing out a message one step with a late subscription's replay: each message reaches a late
    joiner once, from the history or live, never both and never out of order.
    ``targets`` caches its QoS-compatible subscriptions as of registry ``generation`` (deliver runs per message).
    """

    topic: str
    qos: QoSProfile
    log: LocalPublicationLog
    history: deque | None
    lock: threading.RLock | None = None
    targets: list[IntraProcessSubscription] = field(default_factory=list)
    generation: int = -1


class IntraProcessManager:
    """The container-wide registry that routes published objects to in-process subscriptions."""

    def __init__(self, on_callback_error: Callable[[Any, BaseException], None] | None = None,
                 make_wakeup: WakeupFactory = GuardConditionWakeup) -> None:
        """``on_callback_error(node, exc)`` gets what an inline subscription callback raised (the container
        handles it as that component's failure); without it the exception propagates. ``make_wakeup`` is how
        the executor that runs the subscribers is woken (the container passes its executor model's)."""
        self.on_callback_error = on_callback_error
        self.make_wakeup = make_wakeup
        self._lock = threading.Lock()
        self._subscriptions: dict[str, list[IntraProcessSubscription]] = {}
        self._publications: dict[str, list[IntraProcessPublication]] = {}
        self._retired: dict[str, deque[LocalPublicationLog]] = {}
        self._generation = 0  # changes with every subscription added or removed

    def add_publication(self, topic: str, qos: QoSProfile) -> IntraProcessPublication:
        if is_transient_local(qos):
            # The log covers the whole history: every kept sample a late DDS reader gets is known as local.
            kept = kept_messages(qos)
            publication = IntraProcessPublication(topic, qos, LocalPublicationLog(kept), deque(maxlen=kept),
                                                  threading.RLock())
        else:
            publication = IntraProcessPublication(topic, qos, LocalPublicationLog(qos.depth), None)
        with self._lock:
            self._publications.setdefault(topic, []).append(publication)
        return publication

    def add_subscription(self, subscription: IntraProcessSubscription) -> None:
        """Register a subscription. A transient_local one gets the messages the compatible transient_local
        publishers keep, at once, as a late-joining DDS reader gets a writer's history.

        As rclcpp's intra-process manager does: both ends must be transient_local (a volatile subscription
        gets nothing kept), and the subscription gets at most its own depth of them (keep_last), the newest,
        in publish order. Their receive stamp is the replay's time, their source stamp the publish time.
        Each such publisher's lock is held from before the registration until the replay is done, so a
        message published meanwhile is either kept and replayed or delivered live after the replay.
        """
        if not is_transient_local(subscription.qos):
            with self._lock:
                self._register(subscription)
            return
        while True:
            with self._lock:
                latched = self._latched_publications(subscription)
            with contextlib.ExitStack() as held:
                for publication in latched:
                    held.enter_context(publication.lock)  # type: ignore[arg-type]  # transient_local: set
                with self._lock:
                    if self._latched_publications(subscription) != latched:
                        continue  # a latched publisher came or went meanwhile: lock the current set
                    self._register(subscription)
                self._replay(subscription, latched)
                return

    def _register(self, subscription: IntraProcessSubscription) -> None:
        self._subscriptions.setdefault(subscription.topic, []).append(subscription)
        self._generation += 1

    def _latched_publications(self, subscription: IntraProcessSubscription) -> list[IntraProcessPublication]:
        """The transient_local publications that serve ``subscription`` their history, in the order their
        locks are taken (caller holds ``_lock``)."""
        return sorted((p for p in self._publications.get(subscription.topic, ())
                       if p.history is not None and qos_compatible(p.qos, subscription.qos)), key=id)

    @staticmethod
    def _replay(subscription: IntraProcessSubscription, latched: list[IntraProcessPublication]) -> None:
        # Merged by publish time; each publisher's own messages stay in the order it published them.
        kept = list(heapq.merge(*(publication.history for publication in latched),  # type: ignore[misc]
                                key=lambda item: item[1]))
        if subscription.qos.history != HistoryPolicy.KEEP_ALL:
            kept = kept[-max(subscription.qos.depth, 1):]
        for message, published_ns in kept:
            subscription.offer(message, (published_ns, time.time_ns()))

    def remove_publication(self, publication: IntraProcessPublication) -> None:
        """Unregister a publication; its DDS write log stays recognisable while the topic has in-process
        subscriptions: their DDS readers may not have taken its last samples yet."""
        with self._lock:
            _remove(self._publications, publication.topic, publication)
            if publication.topic in self._subscriptions:
                retired = self._retired.setdefault(publication.topic, deque(maxlen=RETIRED_LOGS_PER_TOPIC))
                retired.append(publication.log)

    def remove_subscription(self, subscription: IntraProcessSubscription) -> None:
        """Unregister and close a subscription: once this returns, no publisher calls into it any more."""
        with self._lock:
            _remove(self._subscriptions, subscription.topic, subscription)
            if subscription.topic not in self._subscriptions:
                self._retired.pop(subscription.topic, None)  # nobody left to take a retired writer's samples
            self._generation += 1
        subscription.close()

    def subscription_count(self, publication: IntraProcessPublication) -> int:
        """How many in-process subscriptions may receive from this publication (QoS-compatible)."""
        return len(self._targets(publication))

    def _targets(self, publication: IntraProcessPublication) -> list[IntraProcessSubscription]:
        """``publication.targets``, recomputed once the registry changed. A subscription removed meanwhile
        may still be offered a message: closed first, it ignores it."""
        if publication.generation != self._generation:
            with self._lock:
                publication.targets = [s for s in self._subscriptions.get(publication.topic, ())
                                       if qos_compatible(publication.qos, s.qos)]
                publication.generation = self._generation
        return publication.targets

    def deliver(self, publication: IntraProcessPublication, message: Any) -> int:
        """Hand ``message`` to every compatible in-process subscription; returns how many got it."""
        if publication.lock is None:
            return self._offer(publication, message)
        with publication.lock:  # one step with a late subscription's replay (add_subscription)
            return self._offer(publication, message)

    def _offer(self, publication: IntraProcessPublication, message: Any) -> int:
        now = time.time_ns()
        if publication.history is not None:
            publication.history.append((message, now))
        targets = self._targets(publication)
        for subscription in targets:
            subscription.offer(message, (now, now))
        return len(targets)

    def has_publication(self, topic: str) -> bool:
        """Whether any publisher of this container is registered on ``topic``."""
        with self._lock:
            return bool(self._publications.get(topic))

    def is_local_publication(self, topic: str, sequence: int | None, source_timestamp: int) -> bool:
        """Whether a DDS sample on ``topic`` was written by a publisher in this container (one destroyed since
        included)."""
        if sequence is None:
            return False
        with self._lock:
            logs = [p.log for p in self._publications.get(topic, ())] + list(self._retired.get(topic, ()))
        return any(log.contains(sequence, source_timestamp) for log in logs)


def _remove(registry: dict[str, list], topic: str, entry: object) -> None:
    entries = registry.get(topic, [])
    if entry in entries:
        entries.remove(entry)
    if not entries:
        registry.pop(topic, None)
