"""A recorder stopped and started again many times keeps the final counts of its last bags only.

``~/get_stats`` used to answer the final counts of every bag the recorder had closed since it was loaded: about
700 bytes of JSON per bag, held in the container for good and sent in every reply. The fuzz benchmark's recorder
closes about a thousand bags in 50 000 requests; its container grew by about 6 MiB per 1000 bags (measured over
DDS, the stop / start / get_stats cycle alone) and each ``get_stats`` reply had grown to half a megabyte.

In-process: a container's manager with one recorder; the test drives the recorder's services from a plain rclpy
node in the same context, as any client would.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterator

import pytest
from rclpy.node import Node
from std_srvs.srv import Trigger

from component_container.component_manager import ComponentManager
from component_container.startup_file import load_request
from components.recorder.recorder import FINISHED_STATS_KEPT
from ipc_testing import call, in_process_manager

RECORDER = "finished_stats_recorder"


@pytest.fixture()
def manager() -> Iterator[ComponentManager]:
    with in_process_manager("finished_stats_test") as manager:
        yield manager


@pytest.fixture()
def client(manager: ComponentManager) -> Iterator[Node]:
    node = Node("finished_stats_client", context=manager.context)
    try:
        yield node
    finally:
        node.destroy_node()


def trigger(node: Node, service: str) -> Trigger.Response:
    client = node.create_client(Trigger, f"/{RECORDER}/{service}")
    try:
        return call(node, client, Trigger.Request(), again=service == "get_stats")
    finally:
        node.destroy_client(client)


def test_get_stats_keeps_the_last_bags_and_counts_them_all(manager: ComponentManager, client: Node,
                                                           tmp_path: Path) -> None:
    uri = tmp_path / "cycled"
    manager.load(load_request({"package": "components", "plugin": "components::Recorder", "name": RECORDER,
                               "parameters": {"storage.uri": str(uri), "record.topics": ["/nobody_publishes"]}}, 1))
    sizes: list[int] = []
    cycles = 3 * FINISHED_STATS_KEPT
    for cycle in range(cycles):
        assert trigger(client, "stop_recording").success is not None
        start = trigger(client, "start_recording")
        assert start.success, start.message
        if cycle + 1 in (2 * FINISHED_STATS_KEPT, cycles):
            sizes.append(len(trigger(client, "get_stats").message))
    stats: dict[str, Any] = json.loads(trigger(client, "get_stats").message)
    assert stats["finished_bags"] == cycles
    assert [bag["bag"] for bag in stats["finished"]] == [
        str(uri if n == 0 else uri.with_name(f"{uri.name}_{n}")) for n in range(cycles - FINISHED_STATS_KEPT, cycles)]
    # The reply no longer grows with the bags closed: at 2 K and 3 K bags it holds the same K entries.
    assert abs(sizes[1] - sizes[0]) < 200, sizes
