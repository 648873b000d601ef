"""The base class for nodes that live in a component container.

A component is an ordinary rclpy ``Node``; deriving from :class:`ComponentNode` adds what the container
provides on top of rclpy: when loaded with ``use_intra_process_comms``, ``create_publisher`` and
``create_subscription`` return endpoints that take part in the container's intra-process manager
(component_container.intra_process) while still talking to the rest of the ROS graph over DDS.
``create_action_server`` and ``create_action_client`` return rclpy action endpoints that can publish their
service events as Kilted's action introspection does (component_container.action_introspection).
"""
from __future__ import annotations

import copy
import functools
import inspect
import pathlib
import sys
import time
from typing import Any, Callable

from rclpy.action import ActionClient, ActionServer
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, QoSProfile
from rclpy.subscription import Subscription

from component_container.action_introspection import action_client, action_server
from component_container.bag_root import confine
from component_container.health import Health
from component_container.intra_process import (
    IntraProcessManager,
    IntraProcessPublication,
    IntraProcessSubscription,
)
from component_container.publish_counts import PublishCounter


# See IntraProcessPublisher: how many published objects are watched for reuse (and copied while watching).
REUSE_WATCH = 3
_OWN_REFERENCES = 2
# How long a publisher trusts the count of DDS readers it last read (IntraProcessPublisher._dds_readers).
DDS_COUNT_TTL_NS = 5_000_000


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

    #: The container's ``--bag-root`` (resolved), set at load before ``__init__`` runs; None without one. Every
    #: path a component takes from a request or a service call goes through :meth:`resolve_path`.
    bag_root: pathlib.Path | None = None

    #: Set by the container at load, before ``__init__`` runs: loads a LoadNode request as a component owned by
    #: this one (see :meth:`load_owned_component`). None outside a container.
    component_loader: Callable[[Any], Node] | None = None

    def __init__(self, node_name: str, *, intra_process_manager: IntraProcessManager | None = None,
                 **kwargs: Any) -> None:
        self._ipm = intra_process_manager
        self._ipc_publishers: list[IntraProcessPublisher] = []
        self._ipc_subscriptions: list[IntraProcessSubscriber] = []
        # Publishers whose messages the container reports (component_container.publish_counts); rclpy's own,
        # made while Node.__init__ runs (/parameter_events), are not among them. Names mangled (``__``), as
        # components subclass this class and name their own attributes as they like (``self._count = ...``).
        self.__counted: list[IntraProcessPublisher | CountingPublisher] | None = None
        super().__init__(node_name, **kwargs)
        self.__counted = []

    @property
    def uses_intra_process(self) -> bool:
        return self._ipm is not None

    def resolve_path(self, parameter: str, value: str) -> pathlib.Path:
        """The path that ``parameter`` names, confined to the container's bag root if it has one.

        Without a bag root, ``Path(value)`` (relative to the working directory, as rosbag2 does). With one,
        relative values are taken inside the root and anything resolving outside it (``..``, absolute paths,
        symlinks) raises ValueError naming ``parameter``: the load service answers anyone on the ROS domain.
        """
        return pathlib.Path(value) if self.bag_root is None else confine(self.bag_root, parameter, value)

    def load_owned_component(self, request: Any) -> Node:
        """Load another component (a ``composition_interfaces/LoadNode`` request) into this container, as the
        load service would: listed by ListNodes, run by the container's executor, in its intra-process manager.
        It is unloaded with this one, before it. ValueError outside a container; the container's
        ComponentConstructionError (or LoadRequestError) when the request fails."""
        if self.component_loader is None:
            raise ValueError(f"{request.plugin_name} can only be loaded by a component running in a container")
        return self.component_loader(request)

    def has_local_publisher(self, topic: str) -> bool:
        """Whether a component of this container publishes ``topic`` (resolved name) through intra-process."""
        return self._ipm is not None and self._ipm.has_publication(topic)

    def health(self) -> Health | None:
        """This component's status for ``/diagnostics``; None means "running" with no details.

        Called about once a second from the container's diagnostics thread: must be quick and thread-safe.
        """
        return None

    def work_left(self) -> Health | None:
        """What this component still does after it was unloaded (a recorder's uploads going on in a process
        of their own), for ``/diagnostics``; None: nothing. The container asks once a second after the unload,
        until it answers None; it must not use the destroyed node's ROS handles."""
        return None

    def publish_counters(self) -> list[tuple[str, PublishCounter]]:
        """``(topic, counter)`` of every publisher this component created (thread-safe: a snapshot)."""
        publishers = list(self.__counted or ())
        return [(publisher.topic_name, publisher.publish_counter) for publisher in publishers]

    def create_publisher(self, msg_type: Any, topic: str, qos_profile: QoSProfile | int,
                         **kwargs: Any) -> Publisher:
        """rclpy's create_publisher; the publisher counts what it publishes, and takes part in intra-process
        delivery when the component does."""
        if self._ipm is None:
            kwargs.setdefault("publisher_class", CountingPublisher)
            publisher = super().create_publisher(msg_type, topic, qos_profile, **kwargs)
            if isinstance(publisher, CountingPublisher):
                self.__count(publisher)
            return publisher
        wrapper = IntraProcessPublisher(super().create_publisher(msg_type, topic, qos_profile, **kwargs),
                                        self._ipm, self.get_logger())
        self._ipc_publishers.append(wrapper)
        self.__count(wrapper)
        return wrapper  # type: ignore[return-value]  # duck-types Publisher

    def __count(self, publisher: IntraProcessPublisher | CountingPublisher) -> None:
        if self.__counted is not None:
            self.__counted.append(publisher)

    def create_action_server(self, action_type: Any, action_name: str, execute_callback: Callable[..., Any],
                             **kwargs: Any) -> ActionServer:
        """rclpy's ``ActionServer(self, ...)`` (same arguments) with Kilted's ``configure_introspection``."""
        return action_server(self, action_type, action_name, execute_callback, **kwargs)

    def create_action_client(self, action_type: Any, action_name: str, **kwargs: Any) -> ActionClient:
        """rclpy's ``ActionClient(self, ...)`` (same arguments) with Kilted's ``configure_introspection``."""
        return action_client(self, action_type, action_name, **kwargs)

    def create_subscription(self, msg_type: Any, topic: str, callback: Callable[..., None],
                            qos_profile: QoSProfile | int, *, intra_process_inline: bool = False,
                            intra_process_only: bool = False, **kwargs: Any) -> Subscription:
        """rclpy's create_subscription, taking part in intra-process delivery when the component does.

        ``intra_process_inline=True`` runs the callback for in-process messages directly in the publisher's
        thread, inside ``publish()``, instead of queueing it for the executor: no queue, no executor wake-up.
        Only for callbacks that are thread-safe, never block and never raise — the recorder's intake, which
        just hands the message to its writer thread, is the case it exists for.

        ``intra_process_only=True`` takes messages from publishers of this container only: no DDS reader is
        created, so nothing published on other computers is sent here over the network (a fleet recorder
        records what its own computer publishes). The subscription is then not on the ROS graph.
        """
        if self._ipm is None:
            if intra_process_only:
                raise ValueError(f"a subscription to {topic} limited to this container's publishers needs "
                                 "intra-process comms (load with use_intra_process_comms:=true)")
            return super().create_subscription(msg_type, topic, callback, qos_profile, **kwargs)
        subscriber = IntraProcessSubscriber(self, self._ipm, msg_type, topic, callback, qos_profile,
                                            inline=intra_process_inline, dds=not intra_process_only, **kwargs)
        self._ipc_subscriptions.append(subscriber)
        return subscriber  # type: ignore[return-value]  # duck-types Subscription

    def destroy_publisher(self, publisher: Any) -> bool:
        if publisher in (self.__counted or ()):
            self.__counted.remove(publisher)
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
            if subscription is None:  # intra-process only
                return True
        return super().destroy_subscription(subscription)

    def destroy_node(self) -> None:
        """Leave the intra-process manager first (no publisher can deliver here any more), then destroy the
        node; the rcl node is destroyed even if unregistering fails.

        The node's action servers and clients go too: rclpy's ``destroy_node`` leaves them (they are waitables),
        and each keeps the rcl node, and so its services and topics, alive on the graph after the unload, with
        rcl_action's introspection publishers (Kilted) still offering their transient-local history."""
        try:
            for endpoint in [w for w in self.waitables if isinstance(w, (ActionServer, ActionClient))]:
                endpoint.destroy()
            for subscription in list(self._ipc_subscriptions):
                self.destroy_subscription(subscription)
            for publisher in list(self._ipc_publishers):
                self.destroy_publisher(publisher)
        finally:
            super().destroy_node()


class CountingPublisher(Publisher):
    """rclpy's Publisher, counting what it publishes (a component's publisher without intra-process)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.publish_counter = PublishCounter()

    def publish(self, msg: Any) -> None:
        super().publish(msg)
        self.publish_counter.count(msg)


class IntraProcessPublisher:
    """Publishes a message object to in-process subscriptions by reference, and to DDS when needed.

    The reuse rule. rclcpp moves a message published by ``unique_ptr`` (zero-copy) and copies one published by
    const reference. Python cannot tell the two apart, and a publisher that fills and publishes one object
    again and again is legal in plain rclpy; delivered by reference, every in-process subscriber and the
    recorder would see it change under them. So the first ``REUSE_WATCH`` publishes go in-process as copies
    while the publisher shows what it does, and the last ``REUSE_WATCH`` objects are remembered: publishing
    one of them again switches this publisher to copies for good (one warning). A publisher that builds a new
    object per publish is delivered by reference from then on, at the cost of a few identity checks.
    """

    def __init__(self, publisher: Publisher, manager: IntraProcessManager, logger: Any) -> None:
        self.publisher = publisher
        self._manager = manager
        self._logger = logger
        self._publication: IntraProcessPublication = manager.add_publication(publisher.topic_name,
                                                                             publisher.qos_profile)
        self._always_dds = publisher.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        self._recent: list[Any] = [None] * REUSE_WATCH
        self._published = 0
        self.reuses_messages = False
        self._dds_count = 0
        self._dds_count_read_ns = -(1 << 62)
        self.publish_counter = PublishCounter()

    def publish(self, msg: Any) -> None:
        """Deliver ``msg`` in-process (by reference unless the reuse rule says copy) and, if needed, over DDS."""
        local = self._manager.deliver(self._publication, copy.deepcopy(msg) if self._must_copy(msg) else msg)
        # DDS only for readers outside the intra-process set; transient_local keeps the DDS history whole.
        if self._always_dds or self._dds_readers() > local:
            self._publication.log.record(lambda: self.publisher.publish(msg))
        self.publish_counter.count(msg)

    def _dds_readers(self) -> int:
        """The DDS readers matched to this publisher (its in-process subscriptions' own among them).

        Read at most every DDS_COUNT_TTL_NS: the read costs microseconds, which a publisher at kilohertz rates
        would pay on every publish. A reader matched since then gets this publisher's samples up to 5 ms
        later; matching itself takes DDS discovery far longer, and no volatile reader can count on the first
        samples after it (transient_local publishers always write to DDS).
        """
        now = time.monotonic_ns()
        if now - self._dds_count_read_ns >= DDS_COUNT_TTL_NS:
            self._dds_count = self.publisher.get_subscription_count()
            self._dds_count_read_ns = now
        return self._dds_count

    def local_subscription_count(self) -> int:
        """In-process subscriptions this publisher delivers to (QoS-compatible ones)."""
        return self._manager.subscription_count(self._publication)

    def publish_recorded(self, serialized: bytes | memoryview, make_message: Callable[[], Any]) -> None:
        """Publish a message that exists as CDR bytes (a bag's): in-process subscribers get the object
        ``make_message()`` builds, made only if one exists, and DDS readers get ``serialized`` as it is.

        The object is new and never held by the caller, so the reuse rule does not apply to it. A
        transient_local publisher makes it even with no subscriber yet: it keeps it for late joiners.
        """
        local = 0
        if self._publication.history is not None or self._manager.subscription_count(self._publication):
            local = self._manager.deliver(self._publication, make_message())
        if self._always_dds or self._dds_readers() > local:
            data = serialized if isinstance(serialized, bytes) else bytes(serialized)  # rclpy publishes bytes only
            self._publication.log.record(lambda: self.publisher.publish(data))
        self.publish_counter.count_bytes(len(serialized))

    def _must_copy(self, msg: Any) -> bool:
        if self.reuses_messages:
            return True
        recent = self._recent  # a ring of REUSE_WATCH slots; written in place (this runs on every publish)
        for held in recent:
            if held is msg:
                self.reuses_messages = True
                self._logger.warning(
                    f"Publisher on {self.publisher.topic_name} publishes a message object it published before: "
                    "in-process subscribers get copies from now on (publish a new object each time to keep "
                    "delivery zero-copy)")
                return True
        # Forget objects nobody else holds any more, so that watching costs no memory: the slot and
        # getrefcount's argument are this publisher's own two references.
        for index in range(REUSE_WATCH):
            if recent[index] is not None and sys.getrefcount(recent[index]) <= _OWN_REFERENCES:
                recent[index] = None
        recent[self._published % REUSE_WATCH] = msg
        self._published += 1
        return self._published <= REUSE_WATCH

    def unregister(self) -> None:
        self._manager.remove_publication(self._publication)
        self._recent = [None] * REUSE_WATCH

    def __getattr__(self, name: str) -> Any:
        return getattr(self.publisher, name)  # topic_name, qos_profile, get_subscription_count, ...


class IntraProcessSubscriber:
    """An in-process subscription plus (unless ``dds=False``) a DDS reader for publishers outside the container."""

    def __init__(self, node: Node, manager: IntraProcessManager, msg_type: Any, topic: str,
                 callback: Callable[..., None], qos_profile: QoSProfile | int, *, inline: bool = False,
                 dds: bool = True, **kwargs: Any) -> None:
        self._manager = manager
        self._callback = callback
        self._with_info = _takes_message_info(callback)
        self.dds_subscription: Subscription | None = None
        if dds:  # Node's own method, not ComponentNode's override: this is the plain DDS reader.
            self.dds_subscription = Node.create_subscription(
                node, msg_type, topic, self._on_dds_message, qos_profile, **kwargs)
            self.topic_name, qos = self.dds_subscription.topic_name, self.dds_subscription.qos_profile
        else:
            self.topic_name = node.resolve_topic_name(topic)
            qos = qos_profile if isinstance(qos_profile, QoSProfile) else QoSProfile(depth=qos_profile)
        self._wakeup = manager.make_wakeup(node, self._drain, kwargs.get("callback_group"))
        on_error = (functools.partial(manager.on_callback_error, node)
                    if manager.on_callback_error is not None else None)
        self.queue = IntraProcessSubscription(self.topic_name, qos,
                                              self._wakeup.trigger, self._deliver if inline else None, on_error)
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
            self._wakeup.trigger()  # more arrived meanwhile: run again after others had their turn

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
        self._wakeup.destroy()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.dds_subscription, name)  # qos_profile, msg_type, handle, ...


def _takes_message_info(callback: Callable[..., None]) -> bool:
    """rclpy's rule: a callback that can be called with the message alone gets only the message."""
    try:
        inspect.signature(callback).bind(object())
    except TypeError:
        return True
    return False
