"""The SDK server's callbacks: clients subscribing to channels, asking for parameters, watching the graph.

They run on the SDK's threads and must stay short: a subscription only records which client wants which
channel (the executor subscribes to the topic at its next tick), a parameter request waits, bounded, for the
executor's answer (ros_parameters).
"""
from __future__ import annotations

import foxglove
from foxglove.websocket import ChannelView, Client, ServerListener

from components.foxglove_bridge.channel_registry import ChannelRegistry
from components.foxglove_bridge.ros_parameters import RosParameters


class BridgeListener(ServerListener):
    """Records subscriptions in the registry and answers parameter requests."""

    def __init__(self, registry: ChannelRegistry, parameters: RosParameters) -> None:
        self._registry = registry
        self._parameters = parameters
        #: whether a client watches the connection graph (the executor then publishes it when it changes)
        self.graph_watched = False

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self._registry.set_client(channel.id, client.id, True)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        self._registry.set_client(channel.id, client.id, False)

    def on_get_parameters(self, client: Client, param_names: list[str],
                          request_id: str | None = None) -> list[foxglove.Parameter]:
        return self._parameters.get(param_names)

    def on_set_parameters(self, client: Client, parameters: list[foxglove.Parameter],
                          request_id: str | None = None) -> list[foxglove.Parameter]:
        return self._parameters.set(parameters)

    def on_connection_graph_subscribe(self) -> None:
        self.graph_watched = True

    def on_connection_graph_unsubscribe(self) -> None:
        self.graph_watched = False
