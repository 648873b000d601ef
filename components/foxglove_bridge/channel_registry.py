"""The channels the bridge advertises: one per topic of the ROS graph, kept current as topics come and go.

A channel carries the topic's messages as CDR (message encoding ``cdr``) with the type's full concatenated
definition as its schema (``ros2msg``, or ``ros2idl`` for types that have only IDL), exactly as the MCAP
storage writes it (baglib.format.message_definitions). Topics with more than one type, and types whose
definition is not installed here, are not advertised (one warning each).

The registry is changed on the executor (:meth:`ChannelRegistry.sync`); the SDK's threads (a client
subscribes) and the bridge's thread (forwarding) read it under its lock.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any, Callable

import foxglove

from baglib.format.message_definitions import message_definition
from components.foxglove_bridge.bridge_options import BridgeOptions
from components.foxglove_bridge.channel_queue import INTAKE_DEPTH, ChannelQueue


@dataclass(eq=False)
class BridgeChannel:
    """An advertised topic: its SDK channel, its intake queue, the clients subscribed and what was sent."""

    topic: str
    type_name: str
    sdk: foxglove.Channel
    queue: ChannelQueue
    clients: set[int] = field(default_factory=set)
    sent: int = 0
    sent_bytes: int = 0
    serialize_errors: int = 0
    #: client id -> messages handed to the SDK for that client (while it was subscribed)
    sent_to: dict[int, int] = field(default_factory=dict)

    @property
    def id(self) -> int:
        return self.sdk.id()


class ChannelRegistry:
    """topic -> :class:`BridgeChannel`, for the topics of the graph that ``options`` advertises."""

    def __init__(self, context: foxglove.Context, options: BridgeOptions, wake: Callable[[], None],
                 clock: Callable[[], int], warn: Callable[[str], None]) -> None:
        self._context = context
        self._options = options
        self._wake = wake
        self._clock = clock
        self._warn = warn
        self._lock = threading.Lock()
        self._channels: dict[str, BridgeChannel] = {}
        self._by_id: dict[int, BridgeChannel] = {}
        self._ignored: set[tuple[str, tuple[str, ...]]] = set()

    def sync(self, topics_and_types: list[tuple[str, list[str]]]) -> None:
        """Advertise the new topics of the graph and close the channels of topics that are gone (or changed
        type)."""
        current = {topic: tuple(types) for topic, types in topics_and_types if self._options.advertises(topic)}
        with self._lock:
            vanished = [c for t, c in self._channels.items() if current.get(t) != (c.type_name,)]
        for channel in vanished:
            self._close(channel)
        for topic, types in current.items():
            if topic not in self._channels and (topic, types) not in self._ignored:
                self._advertise(topic, types)

    def _advertise(self, topic: str, types: tuple[str, ...]) -> None:
        if len(types) != 1:
            self._ignore(topic, types, f"it has more than one type ({', '.join(types)})")
            return
        try:
            encoding, text = message_definition(types[0])
        except (LookupError, ValueError) as exc:
            self._ignore(topic, types, f"no definition of {types[0]} here ({exc})")
            return
        schema = foxglove.Schema(name=types[0], encoding=encoding, data=text.encode())
        queue = ChannelQueue(topic, max(INTAKE_DEPTH, self._options.max_qos_depth), self._options.rate_limit(topic),
                             self._wake, self._clock)
        sdk = foxglove.Channel(topic, schema=schema, message_encoding="cdr", context=self._context)
        channel = BridgeChannel(topic, types[0], sdk, queue)
        with self._lock:
            self._channels[topic] = channel
            self._by_id[channel.id] = channel

    def _ignore(self, topic: str, types: tuple[str, ...], reason: str) -> None:
        self._ignored.add((topic, types))
        self._warn(f"Not advertising {topic}: {reason}")

    def _close(self, channel: BridgeChannel) -> None:
        with self._lock:
            self._channels.pop(channel.topic, None)
            self._by_id.pop(channel.id, None)
        channel.queue.clear()
        channel.sdk.close()  # the SDK unadvertises it (and reports the subscribed clients as unsubscribed)

    def close(self) -> None:
        for channel in self.channels():
            self._close(channel)

    def channels(self) -> list[BridgeChannel]:
        with self._lock:
            return list(self._channels.values())

    def get(self, topic: str) -> BridgeChannel | None:
        with self._lock:
            return self._channels.get(topic)

    def by_id(self, channel_id: int) -> BridgeChannel | None:
        with self._lock:
            return self._by_id.get(channel_id)

    def set_client(self, channel_id: int, client_id: int, subscribed: bool) -> BridgeChannel | None:
        """Record that a client subscribed to (or left) a channel; returns the channel, None if unknown."""
        with self._lock:
            channel = self._by_id.get(channel_id)
            if channel is not None:
                (channel.clients.add if subscribed else channel.clients.discard)(client_id)
            return channel

    def wanted_topics(self) -> set[str]:
        """Topics at least one client is subscribed to: the bridge subscribes to exactly these."""
        with self._lock:
            return {topic for topic, channel in self._channels.items() if channel.clients}

    def stats(self) -> dict[str, dict[str, Any]]:
        """Per channel with traffic or clients: clients, received, sent, dropped, throttled, serialize errors."""
        with self._lock:
            channels = list(self._channels.values())
        return {c.topic: {"clients": sorted(c.clients), "received": c.queue.received, "sent": c.sent,
                          "sent_bytes": c.sent_bytes, "dropped": c.queue.dropped, "throttled": c.queue.throttled,
                          "serialize_errors": c.serialize_errors, "sent_to": dict(c.sent_to)}
                for c in channels if c.clients or c.queue.received}
