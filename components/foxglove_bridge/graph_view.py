"""The ROS graph as Foxglove's connection graph: who publishes and subscribes each topic, who offers each
service. Read on the executor at the polling interval while a client is subscribed to it; published only when
it changed (the SDK sends each client the difference)."""
from __future__ import annotations

from collections import defaultdict

import foxglove
from rclpy.node import Node

Graph = tuple[dict[str, list[str]], dict[str, list[str]], dict[str, list[str]]]


def _full_name(namespace: str, name: str) -> str:
    return f"{namespace.rstrip('/')}/{name}"


def read_graph(node: Node) -> Graph:
    """(published topics, subscribed topics, advertised services): each name -> sorted node names."""
    published: dict[str, list[str]] = {}
    subscribed: dict[str, list[str]] = {}
    for topic, _types in node.get_topic_names_and_types():
        publishers = sorted({_full_name(i.node_namespace, i.node_name)
                             for i in node.get_publishers_info_by_topic(topic)})
        subscribers = sorted({_full_name(i.node_namespace, i.node_name)
                              for i in node.get_subscriptions_info_by_topic(topic)})
        if publishers:
            published[topic] = publishers
        if subscribers:
            subscribed[topic] = subscribers
    services: dict[str, set[str]] = defaultdict(set)
    for name, namespace in node.get_node_names_and_namespaces():
        try:
            offered = node.get_service_names_and_types_by_node(name, namespace)
        except Exception:  # noqa: BLE001 - rclpy's NodeNameNonExistentError: the node left meanwhile
            continue
        for service, _types in offered:
            services[service].add(_full_name(namespace, name))
    return published, subscribed, {service: sorted(nodes) for service, nodes in services.items()}


def connection_graph(graph: Graph) -> foxglove.ConnectionGraph:
    published, subscribed, services = graph
    result = foxglove.ConnectionGraph()
    for topic, nodes in published.items():
        result.set_published_topic(topic, nodes)
    for topic, nodes in subscribed.items():
        result.set_subscribed_topic(topic, nodes)
    for service, nodes in services.items():
        result.set_advertised_service(service, nodes)
    return result
