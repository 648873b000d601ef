"""The base class for nodes that live in a component container.

A component is an ordinary rclpy ``Node``; deriving from :class:`ComponentNode` adds what the container
provides on top of rclpy: when loaded with ``use_intra_process_comms``, ``create_publisher`` and
``create_subscription`` return endpoints that take part in the container's intra-process manager
(component_container.intra_process) while still talking to the rest of the ROS graph over DDS.
"""
from __future__ import annotations

import inspect
from typing import Any, Callable

from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, QoSProfile
from rclpy.subscription import Subscription

from component_container.health import Health
from component_container.intra_process import (
    IntraProcessManager,
    IntraProcessPublication,
    IntraProcessSubscription,
)


class ComponentNode(Node):
    """An rclpy node that a component container can load by plugin name.

    Constructors of components accept rclpy's ``Node`` keyword arguments (``context``, ``cli_args``,
    ``use_global_arguments``, ``parameter_overrides`` ...) plus ``intra_process_manager`` and pass them on,
    exactly as rclcpp components accept ``rclcpp::NodeOptions``.
    """

    #: Seconds the container grants this component's ``destroy_node`` when it is unloaded (the container's
    #: ``--shutdown-timeout``, set at load). A component that waits on something (a writer thread, a disk)
    #: must give up within it; the container abandons a destroy that takes longer.
    shutdown_timeout: float = 10.0

    def __init__(self, node_name: str, *, intra_process_manager: IntraProcessManager | None = None,
                 **kwargs: Any) -> None:
        self._ipm = intra_process_manager
        self._ipc_publishers: list[IntraProcessPublisher] = []
        self._ipc_subscriptions: list[IntraProcessSubscriber] = []
        super().__init__(node_name, **kwargs)

    @property
    def uses_intra_process(self) -> bool:
        return self._ipm is not None

    def health(self) -> Health | None:
        """This component's status for ``/diagnostics``; None means "running" with no details.

        Called about once a second from the container's diagnostics thread: must be quick and thread-safe.
        """
        return None

    def create_publisher(self, msg_type: Any, topic: str, qos_profile: QoSProfile | int,
                         **kwargs: Any) -> Publisher:
        publisher = super().create_publisher(msg_type, topic, qos_profile, **kwargs)
        if self._ipm is None:
            return publisher
        wrapper = IntraProcessPublisher(publisher, self._ipm)
        self._ipc_publishers.append(wrapper)
        return wrapper  # type: ignore[return-value]  # duck-types Publisher

    def create_subscription(self, msg_type: Any, topic: str, callback: Callable[..., None],
                            qos_profile: QoSProfile | int, *, intra_process_inline: bool = False,
                            **kwargs: Any) -> Subscription:
        """rclpy's create_subscription, taking part in intra-process delivery when the component does.

        ``intra_process_inline=True`` runs the callback for in-process messages directly in the publisher's
        thread, inside ``publish()``, instead of queueing it for the executor: no queue, no executor wake-up.
        Only for callbacks that are thread-safe, never block and never raise — the recorder's intake, which
        just hands the message to its writer thread, is the case it exists for.
        """
        if self._ipm is None:
            return super().create_subscription(msg_type, topic, callback, qos_profile, **kwargs)
        subscriber = IntraProcessSubscriber(self, self._ipm, msg_type, topic, callback, qos_profile,
                                            inline=intra_process_inline, **kwargs)
        self._ipc_subscriptions.append(subscriber)
        return subscriber  # type: ignore[return-value]  # duck-types Subscription

    def destroy_publisher(self, publisher: Any) -> bool:
        if isinstance(publisher, IntraProcessPublisher):
            self._ipc_publishers.remove(publisher)
            publisher.unregister()
            publisher = publisher.publisher
        return super().destroy_publisher(publisher)

    def destroy_subscription(self, subscription: Any) -> bool:
        if isinstance(subscription, IntraProcessSubscriber):
            self._ipc_subscriptions.remove(subscription)
            subscription.unregister()
            subscription = subscription.dds_subscription
        return super().destroy_subscription(subscription)

    def destroy_node(self) -> None:
        for publisher in list(self._ipc_publishers):
            self.destroy_publisher(publisher)
        for subscription in list(self._ipc_subscriptions):
            self.destroy_subscription(subscription)
        super().destroy_node()


class IntraProcessPublisher:
    """Publishes a message object to in-process subscriptions by reference, and to DDS when needed."""

    def __init__(self, publisher: Publisher, manager: IntraProcessManager) -> None:
        self.publisher = publisher
        self._manager = manager
        self._publication: IntraProcessPublication = manager.add_publication(publisher.topic_name,
                                                                             publisher.qos_profile)
        self._always_dds = publisher.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL

    def publish(self, msg: Any) -> None:
        """Deliver ``msg`` (which then belongs to the subscribers) in-process and, if needed, over DDS."""
        local = self._manager.deliver(self._publication, msg)
        # DDS only for readers outside the intra-process set; transient_local keeps the DDS history whole.
        if self._always_dds or self.publisher.get_subscription_count() > local:
            self._publication.log.record(lambda: self.publisher.publish(msg))

    def unregister(self) -> None:
        self._manager.remove_publication(self._publication)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.publisher, name)  # topic_name, qos_profile, get_subscription_count, ...


class IntraProcessSubscriber:
    """An in-process subscription plus a DDS reader for publishers outside the container."""

    def __init__(self, node: Node, manager: IntraProcessManager, msg_type: Any, topic: str,
                 callback: Callable[..., None], qos_profile: QoSProfile | int, *, inline: bool = False,
                 **kwargs: Any) -> None:
        self._manager = manager
        self._callback = callback
        self._with_info = _takes_message_info(callback)
        # Node's own method, not ComponentNode's override: this is the plain DDS reader.
        self.dds_subscription = Node.create_subscription(
            node, msg_type, topic, self._on_dds_message, qos_profile, **kwargs)
        self.topic_name = self.dds_subscription.topic_name
        self._guard = node.create_guard_condition(self._drain, kwargs.get("callback_group"))
        self._node = node
        self.queue = IntraProcessSubscription(self.topic_name, self.dds_subscription.qos_profile,
                                              self._guard.trigger, self._deliver if inline else None)
        manager.add_subscription(self.queue)

    @property
    def received_count(self) -> int:
        """Messages offered in-process (including those later dropped)."""
        return self.queue.received

    @property
    def dropped_count(self) -> int:
        """Messages dropped because this subscription's keep_last queue was full."""
        return self.queue.dropped

    def _drain(self) -> None:
        for _ in range(len(self.queue.queue)):
            item = self.queue.take()
            if item is None:
                return
            self._deliver(*item)
        if self.queue.queue:
            self._guard.trigger()  # more arrived meanwhile: run again after others had their turn

    def _deliver(self, message: Any, stamps: tuple[int, int]) -> None:
        if self._with_info:
            self._callback(message, {"source_timestamp": stamps[0], "received_timestamp": stamps[1],
                                     "publication_sequence_number": None, "reception_sequence_number": None})
        else:
            self._callback(message)

    def _on_dds_message(self, message: Any, info: dict[str, Any]) -> None:
        if self._manager.is_local_publication(self.topic_name, info.get("publication_sequence_number"),
                                              info.get("source_timestamp", 0)):
            return  # already delivered in-process
        if self._with_info:
            self._callback(message, info)
        else:
            self._callback(message)

    def unregister(self) -> None:
        self._manager.remove_subscription(self.queue)
        self._node.destroy_guard_condition(self._guard)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.dds_subscription, name)  # qos_profile, msg_type, handle, ...


def _takes_message_info(callback: Callable[..., None]) -> bool:
    """rclpy's rule: a callback that can be called with the message alone gets only the message."""
    try:
        inspect.signature(callback).bind(object())
    except TypeError:
        return True
    return False
