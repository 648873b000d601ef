"""The channels the bridge advertises: one per topic of the ROS graph, kept current as topics come and go.

A channel carries the topic's messages as CDR (message encoding ``cdr``) with the type's full concatenated
definition as its schema (``ros2msg``, or ``ros2idl`` for types that have only IDL), exactly as the MCAP
storage writes it (baglib.format.message_definitions). Topics with more than one type, and types whose
definition is not installed here, are not advertised (one warning each). With ``video.codec`` set, each
``sensor_msgs/msg/Image`` topic also gets a video channel ``<image>/video`` (video_feed), unless the graph has a
topic of that name.

The registry is changed on the executor (:meth:`ChannelRegistry.sync`); the SDK's threads (a client
subscribes) and the bridge's thread (forwarding) read it under its lock.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any, Callable

import foxglove

from baglib.format import cdr_fast
from baglib.format.message_definitions import message_definition
from components.foxglove_bridge.bridge_options import BridgeOptions
from components.foxglove_bridge.channel_queue import INTAKE_DEPTH, ChannelQueue
from components.foxglove_bridge.video_feed import IMAGE_TYPE, VIDEO_TYPE, VideoFeed, video_topic


def cdr_bytes(message: Any) -> bytes:
    """``message`` as one CDR ``bytes`` object (what the SDK takes): DDS samples as they are."""
    if isinstance(message, bytes):
        return message
    if isinstance(message, (bytearray, memoryview)):
        return bytes(message)
    data = cdr_fast.serialize(message)
    return data if isinstance(data, bytes) else bytes(data)


@dataclass(eq=False)
class BridgeChannel:
    """An advertised topic: its SDK channel, its intake queue, the clients subscribed and what was sent."""

    topic: str
    type_name: str
    sdk: foxglove.Channel
    #: the intake: a ChannelQueue of the topic's messages, or a video channel's VideoFeed (its image topic)
    queue: ChannelQueue | VideoFeed
    clients: set[int] = field(default_factory=set)
    sent: int = 0
    sent_bytes: int = 0
    serialize_errors: int = 0
    #: client id -> messages handed to the SDK for that client (while it was subscribed)
    sent_to: dict[int, int] = field(default_factory=dict)

    @property
    def id(self) -> int:
        return self.sdk.id()

    def serialize(self, message: Any, warn: Callable[[str], None]) -> bytes | None:
        """``message`` as CDR; None for a message that cannot be serialized (counted, one warning per channel:
        it costs that message only)."""
        try:
            return cdr_bytes(message)
        except Exception as exc:  # noqa: BLE001 - any failure of a type's serializer
            self.serialize_errors += 1
            if self.serialize_errors == 1:
                warn(f"Cannot serialize a message of {self.topic} ({type(exc).__name__}: {exc}); "
                     "its messages are dropped")
            return None

    def send(self, data: bytes, log_time: int) -> None:
        """Hand ``data`` to the SDK for the subscribed clients, counted. One thread per channel calls it: the
        bridge's (forwarder), or a video channel's encoder (video_feed)."""
        self.sdk.log(data, log_time=log_time)
        self.sent += 1
        self.sent_bytes += len(data)
        for client in tuple(self.clients):
            self.sent_to[client] = self.sent_to.get(client, 0) + 1


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
        graph = {topic: tuple(types) for topic, types in topics_and_types}
        current = {topic: types for topic, types in graph.items() if self._options.advertises(topic)}
        videos = {video_topic(topic): topic for topic, types in current.items()
                  if self._options.video is not None and types == (IMAGE_TYPE,) and video_topic(topic) not in graph
                  and self._options.advertises(video_topic(topic))}
        with self._lock:
            vanished = [c for t, c in self._channels.items()
                        if (videos.get(t) != c.queue.source if isinstance(c.queue, VideoFeed)
                            else current.get(t) != (c.type_name,))]
        for channel in vanished:
            self._close(channel)
        for topic, types in current.items():
            if topic not in self._channels and (topic, types) not in self._ignored:
                self._advertise(topic, types)
        for topic, source in videos.items():
            if topic not in self._channels and (topic, (VIDEO_TYPE,)) not in self._ignored:
                self._advertise_video(topic, source)

    def _advertise(self, topic: str, types: tuple[str, ...]) -> None:
        if len(types) != 1:
            self._ignore(topic, types, f"it has more than one type ({', '.join(types)})")
            return
        try:
            encoding, text = message_definition(types[0])
        except (LookupError, ValueError) as exc:
            self._ignore(topic, types, f"no definition of {types[0]} here ({exc})")
            return
        queue = ChannelQueue(topic, max(INTAKE_DEPTH, self._options.max_qos_depth), self._options.rate_limit(topic),
                             self._wake, self._clock)
        self._add(BridgeChannel(topic, types[0], self._sdk_channel(topic, types[0], encoding, text), queue))

    def _advertise_video(self, topic: str, source: str) -> None:
        """``source`` (an Image topic) as video on ``topic``, encoded by a VideoFeed while a client watches."""
        assert self._options.video is not None
        try:
            encoding, text = message_definition(VIDEO_TYPE)  # built at install (foxglove_msgs)
        except (LookupError, ValueError) as exc:
            self._ignore(topic, (VIDEO_TYPE,), f"no definition of {VIDEO_TYPE} here ({exc})")
            return

        def send(message: Any, keyframe: bool) -> None:  # on the encoder's thread, once ``channel`` exists
            data = channel.serialize(message, self._warn)
            if data is not None:
                channel.send(data, self._clock())

        feed = VideoFeed(source, self._options.video, send, self._warn)
        channel = BridgeChannel(topic, VIDEO_TYPE, self._sdk_channel(topic, VIDEO_TYPE, encoding, text), feed)
        self._add(channel)

    def _sdk_channel(self, topic: str, type_name: str, encoding: str, text: str) -> foxglove.Channel:
        schema = foxglove.Schema(name=type_name, encoding=encoding, data=text.encode())
        return foxglove.Channel(topic, schema=schema, message_encoding="cdr", context=self._context)

    def _add(self, channel: BridgeChannel) -> None:
        with self._lock:
            self._channels[channel.topic] = channel
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
        """Record that a client subscribed to (or left) a channel; returns the channel, None if unknown. A client
        joining a video channel that is encoding gets a keyframe first."""
        with self._lock:
            channel = self._by_id.get(channel_id)
            if channel is not None:
                (channel.clients.add if subscribed else channel.clients.discard)(client_id)
        if channel is not None and subscribed and isinstance(channel.queue, VideoFeed):
            channel.queue.client_joined()
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
                          "serialize_errors": c.serialize_errors, "sent_to": dict(c.sent_to),
                          **({"encoder": c.queue.encoder_stats()} if isinstance(c.queue, VideoFeed) else {})}
                for c in channels if c.clients or c.queue.received}
