"""The bridge's ROS subscriptions: one per topic that a client is subscribed to, and none otherwise.

Loaded with ``use_intra_process_comms``, a subscription takes messages of this container's publishers
through the intra-process path, inline in the publisher's thread (the callback only queues the object, see
channel_queue), and those of other processes through its DDS reader as raw CDR (``raw=True``: no
deserialization, no second serialization). Without intra-process comms everything comes over DDS, raw.

Created and destroyed on the executor (:meth:`TopicSubscriptions.apply`), from what the SDK's threads
recorded; destroying one takes it off the ROS graph and forgets what its channel had queued. A video channel's
subscription is to its image topic, deserialized (the encoder needs the pixels), and exists together with its
encoder (video_feed): the encoder starts before the subscription and stops after it.
"""
from __future__ import annotations

from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from baglib.format.message_definitions import message_class
from component_container.component_node import ComponentNode
from components.foxglove_bridge.bridge_options import BridgeOptions
from components.foxglove_bridge.channel_registry import BridgeChannel, ChannelRegistry
from components.foxglove_bridge.video_feed import IMAGE_TYPE, VideoFeed


def subscription_qos(offered: list[QoSProfile], options: BridgeOptions) -> QoSProfile:
    """foxglove_bridge's rule: keep_last with the publishers' summed depth clamped to [min, max]_qos_depth;
    reliable / transient_local only when every publisher offers it."""
    depth = sum(q.depth for q in offered if q.history != HistoryPolicy.KEEP_ALL) or options.min_qos_depth
    reliable = bool(offered) and all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
    transient = bool(offered) and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=min(max(depth, options.min_qos_depth), options.max_qos_depth),
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE)


class TopicSubscriptions:
    """topic -> the bridge node's subscription, matched to the registry's wanted topics by :meth:`apply`."""

    def __init__(self, node: ComponentNode, options: BridgeOptions) -> None:
        self._node = node
        self._options = options
        self._subscriptions: dict[str, Any] = {}
        self._failed: set[str] = set()

    def qos(self, topic: str) -> QoSProfile:
        return subscription_qos([p.qos_profile for p in self._node.get_publishers_info_by_topic(topic)],
                                self._options)

    def apply(self, registry: ChannelRegistry) -> None:
        """Subscribe to the wanted topics not subscribed yet; destroy the subscriptions nobody wants."""
        wanted = registry.wanted_topics()
        for topic in [t for t in self._subscriptions if t not in wanted]:
            self._node.destroy_subscription(self._subscriptions.pop(topic))
            channel = registry.get(topic)
            if channel is not None:
                channel.queue.clear()
            self._node.get_logger().info(f"Unsubscribed from {topic}")
        for topic in wanted - self._subscriptions.keys() - self._failed:
            channel = registry.get(topic)
            if channel is not None:
                self._subscribe(channel)

    def _subscribe(self, channel: BridgeChannel) -> None:
        """Subscribe; a type this process cannot subscribe with is logged once and left alone."""
        kwargs: dict[str, Any] = {"intra_process_inline": True} if self._node.uses_intra_process else {}
        topic, type_name, raw = channel.topic, channel.type_name, True
        if isinstance(channel.queue, VideoFeed):
            topic, type_name, raw = channel.queue.source, IMAGE_TYPE, False
            channel.queue.start()
        try:
            self._subscriptions[channel.topic] = self._node.create_subscription(
                message_class(type_name), topic, channel.queue.offer, self.qos(topic), raw=raw, **kwargs)
        except Exception as exc:  # noqa: BLE001 - any broken installation of a type: that topic only
            self._failed.add(channel.topic)
            channel.queue.clear()
            self._node.get_logger().error(f"Cannot subscribe to {topic} ({type_name}): {type(exc).__name__}: {exc}")
            return
        self._node.get_logger().info(f"Subscribed to {topic} ({type_name}) for {channel.topic}"
                                     if topic != channel.topic else f"Subscribed to {topic} ({type_name})")

    @property
    def topics(self) -> list[str]:
        return sorted(self._subscriptions)

    def close(self) -> None:
        for topic in list(self._subscriptions):
            self._node.destroy_subscription(self._subscriptions.pop(topic))
