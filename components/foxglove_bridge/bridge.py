"""``components::FoxgloveBridge``: the container's topics for Foxglove, over the Foxglove SDK's WebSocket server.

Loaded next to the drivers and the recorder with ``use_intra_process_comms``, it hands Foxglove the frames the
drivers publish without a DDS hop: the bridge subscribes to a topic only while a client is subscribed to its
channel, takes this container's messages by reference (intra-process, inline: the publisher's thread only
queues the object), serializes them on the bridge's own thread and gives the CDR to the SDK, which sends it
to every subscribed client. Topics of other processes come through the same subscription's DDS reader as
raw CDR.

What a client sees: every topic of the graph as a channel (``cdr``, schema ``ros2msg``, see
channel_registry), kept current at ``polling_interval``; the parameters of the graph's nodes
(ros_parameters); the graph's services, called with CDR (ros_services); the connection graph (graph_view);
with ``use_sim_time``, ``/clock`` as the server's time; each image topic also as video, encoded in the bridge
while a client watches (video_feed).
``~/get_stats`` (std_srvs/Trigger) answers the counts per channel as JSON; ``/diagnostics`` shows them too.

A slow client never slows the container: each channel's queue in the bridge is bounded (newest kept, drops
counted), the SDK keeps a bounded outbox per client (``message_backlog_size`` messages, oldest dropped), and
``rate_limits`` caps chosen channels. Parameters: bridge_options. The bridge listens on 127.0.0.1 unless
``address`` says otherwise (docs/security.md), for clients of both names of the protocol (subprotocol_proxy);
the SDK's server itself listens on an ephemeral loopback port behind it.
"""
from __future__ import annotations

import json
import time
from typing import Any

import foxglove
from foxglove.websocket import Capability
from rosgraph_msgs.msg import Clock
from std_srvs.srv import Trigger

from component_container.component_node import ComponentNode
from component_container.health import DROPPED, OK, WARN, Health
from components.foxglove_bridge.bridge_options import BridgeOptions, declare_options
from components.foxglove_bridge.channel_registry import ChannelRegistry
from components.foxglove_bridge.executor_work import WorkQueue
from components.foxglove_bridge.forwarder import Forwarder
from components.foxglove_bridge.graph_view import Graph, connection_graph, read_graph
from components.foxglove_bridge.ros_parameters import RosParameters
from components.foxglove_bridge.ros_services import RosServices
from components.foxglove_bridge.server_listener import BridgeListener
from components.foxglove_bridge.subprotocol_proxy import SubprotocolProxy
from components.foxglove_bridge.topic_subscriptions import TopicSubscriptions

#: s between the housekeeping ticks on the executor (subscribe / unsubscribe, parameter requests)
TICK = 0.05
#: s between two server time messages from /clock (they take the clients' control queue)
TIME_PERIOD = 0.05


class FoxgloveBridge(ComponentNode):
    """A Foxglove WebSocket server for the ROS graph, fed zero-copy from the container (module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("foxglove_bridge", **kwargs)
        self._server: Any = None
        self._proxy: SubprotocolProxy | None = None
        self._forwarder: Forwarder | None = None
        try:
            self._options: BridgeOptions = declare_options(self)
            self._sim_time = bool(self.get_parameter("use_sim_time").value)
            self._fox_context = foxglove.Context()
            self._forwarder = Forwarder(lambda: self._registry.channels(), self._warn,
                                        name=f"foxglove:{self.get_name()}")
            self._registry = ChannelRegistry(self._fox_context, self._options, self._forwarder.wake, self._clock_ns,
                                             self._warn)
            self._topic_subscriptions = TopicSubscriptions(self, self._options)
            self._work = WorkQueue()
            self._ros_parameters = RosParameters(self, self._options, self._work, self._publish_parameters)
            self._listener = BridgeListener(self._registry, self._ros_parameters)
            self._server = self._start_server()
            self._proxy = self._listen()
            self._ros_services = RosServices(self, self._options, self._work, self._server, self._warn)
            self._forwarder.start()
            self._last_time_ns = 0
            self._clock_subscription = (self.create_subscription(Clock, "/clock", self._on_clock, 10)
                                        if self._sim_time else None)
            self._graph: Graph | None = None
            self._reported_drops: dict[str, int] = {}
            self._health_drops = 0
            self._next_sync = 0.0
            self._tick()
            self._tick_timer = self.create_timer(TICK, self._tick)
            self._stats_service = self.create_service(Trigger, "~/get_stats", self._on_get_stats)
        except Exception:
            self._stop()  # no server, thread or channel is left behind by a load that failed
            super().destroy_node()
            raise
        self.get_logger().info(f"Foxglove bridge listening on {self.url}")

    def _start_server(self) -> Any:
        """The SDK's server, on an ephemeral loopback port: clients reach it through :meth:`_listen`'s proxy."""
        capabilities = [Capability.Parameters, Capability.ConnectionGraph, Capability.Services]
        if self._sim_time:
            capabilities.append(Capability.Time)
        return foxglove.start_server(
            name=self.get_fully_qualified_name(), host="127.0.0.1", port=0, capabilities=capabilities,
            server_listener=self._listener, supported_encodings=["cdr"], context=self._fox_context,
            message_backlog_size=self._options.message_backlog_size)

    def _listen(self) -> SubprotocolProxy:
        """The socket clients connect to, on ``address``:``port``, for both names of the protocol
        (subprotocol_proxy)."""
        try:
            return SubprotocolProxy(self._options.address, self._options.port, self._server.port,
                                    name=f"foxglove:{self.get_name()}")
        except OSError as exc:
            raise ValueError(f"parameters 'address'/'port': cannot listen on {self._options.address}:"
                             f"{self._options.port} ({exc})") from None

    @property
    def url(self) -> str:
        assert self._proxy is not None
        host = self._options.address
        return f"ws://{f'[{host}]' if ':' in host else host}:{self._proxy.port}"

    def _clock_ns(self) -> int:
        return self.get_clock().now().nanoseconds if self._sim_time else time.time_ns()

    def _warn(self, text: str) -> None:
        self.get_logger().warning(text)

    # --- the executor ---------------------------------------------------------------------------------------
    def _tick(self) -> None:
        """Match the subscriptions to the clients' wishes, run parameter requests; at the polling interval,
        look at the graph."""
        self._topic_subscriptions.apply(self._registry)
        self._work.run(self._warn)
        now = time.monotonic()
        if now >= self._next_sync:
            self._next_sync = now + self._options.polling_interval
            self._sync_graph()

    def _sync_graph(self) -> None:
        self._registry.sync(self.get_topic_names_and_types())
        self._ros_services.sync(self.get_service_names_and_types())
        self._ros_parameters.prune({f"{ns.rstrip('/')}/{name}" for name, ns in self.get_node_names_and_namespaces()})
        if self._listener.graph_watched:
            graph = read_graph(self)
            if graph != self._graph:
                self._server.publish_connection_graph(connection_graph(graph))
                self._graph = graph
        self._report_drops()

    def _report_drops(self) -> None:
        """One log line per channel whose queue dropped messages since the last look."""
        for topic, stats in self._registry.stats().items():
            dropped = stats["dropped"] - self._reported_drops.get(topic, 0)
            if dropped > 0:
                self._reported_drops[topic] = stats["dropped"]
                reason = ("its encoder skipped them (it fell behind, or held them back for a client's keyframe)"
                          if "encoder" in stats else "the bridge's thread fell behind")
                self._warn(f"Dropped {dropped} messages of {topic}: {reason} ({stats['dropped']} in all)")

    def _on_clock(self, message: Clock) -> None:
        stamp = message.clock.sec * 1_000_000_000 + message.clock.nanosec
        now = time.monotonic_ns()
        if now - self._last_time_ns >= TIME_PERIOD * 1e9:
            self._last_time_ns = now
            self._server.broadcast_time(stamp)

    def _publish_parameters(self, parameters: list[foxglove.Parameter]) -> None:
        self._server.publish_parameter_values(parameters)

    # --- reporting ------------------------------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """Per channel with traffic or clients: clients, received, sent, dropped, throttled, per-client counts;
        a video channel's encoder counts too."""
        return {"url": self.url, "subscriptions": self._topic_subscriptions.topics, "channels": self._registry.stats()}

    def _on_get_stats(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = True, json.dumps(self.stats())
        return response

    def health(self) -> Health:
        """For /diagnostics: WARN while the bridge's queues (or a video channel's encoder) drop messages, OK
        otherwise; ``dropped`` in all, which ``ipc-component top`` shows."""
        channels = self._registry.stats()
        drops = sum(c["dropped"] for c in channels.values())
        new_drops, self._health_drops = drops - self._health_drops, drops
        clients = sorted({client for c in channels.values() for client in c["clients"]})
        values = {"url": self.url, "channels": str(len(self._registry.channels())),
                  "clients subscribed": ", ".join(map(str, clients)) or "none", DROPPED: str(drops)}
        for topic, c in sorted(channels.items()):
            values[topic] = (f"clients {len(c['clients'])}, received {c['received']}, sent {c['sent']}, "
                             f"dropped {c['dropped']}, throttled {c['throttled']}")
            if "encoder" in c:
                values[topic] += ", encoder " + ", ".join(f"{name} {count}" for name, count in c["encoder"].items())
            for client, sent in sorted(c["sent_to"].items()):
                values[f"{topic} -> client {client}"] = f"sent {sent}"
        if new_drops:
            return Health(WARN, f"dropped {new_drops} messages in the last second", values)
        return Health(OK, f"serving {len(clients)} client(s)", values)

    # --- teardown -------------------------------------------------------------------------------------------
    def _stop(self) -> None:
        """Stop the server (clients are disconnected), the subscriptions, the thread; close the channels."""
        if self._server is not None:
            self._server.stop()
        if self._proxy is not None:
            self._proxy.stop()
        for part in ("_topic_subscriptions", "_ros_parameters", "_ros_services"):
            if hasattr(self, part):
                getattr(self, part).close()
        if self._forwarder is not None:
            self._forwarder.stop()
        if hasattr(self, "_registry"):
            self._registry.close()

    def destroy_node(self) -> None:
        self._stop()
        super().destroy_node()
