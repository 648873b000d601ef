"""The one rclpy context of a test process, whose Fast DDS participant lives as long as the process.

Why: every rclpy context is a Fast DDS participant, destroyed with the context's last node. Fast DDS 2.14 (Jazzy's
wheels) can livelock destroying one: ``DomainParticipant::set_listener(nullptr)`` waits for the participant's
discovery callbacks in flight by spinning on a condition variable's ``wait_until`` whose deadline never blocks,
re-taking the listener mutex at once each time; a discovery callback that has begun needs that mutex to finish, so
it never gets it, and the destroying thread spins on (with the GIL held, the whole process stops). It takes a
discovery event arriving at the very moment of destruction, so it is rare per participant; a test run that made a
context per test destroyed about 350 participants in its workers, and two of about twenty runs hung
(docs/limitations.md, Platform, has the stacks). Tests that share this context destroy none: nodes come and go, the
participant stays, held by an anchor node, until the process ends (pytest-xdist ends a worker that does not exit
within 10 s of its last test).

A test that needs a second participant in the process (the DDS path between two contexts) still makes a context
of its own; every other in-process node belongs here, and nothing shuts this context down.

Except the clients of container processes (:func:`client_context`): a participant that outlives a SIGKILLed
container keeps it as a ghost until its lease ends (20 s), and meanwhile finds a container started after it
about 2.5 s late (a participant kept across kills: 3.0 s from start to the first answered ListNodes; a new one:
0.55 s). So the clients have a context of their own, kept from test to test while no ghost is in its graph, and
replaced after a test that left one: a participant's GUID prefix holds its process id (bytes 4-5, little-endian,
the low 16 bits: Fast DDS 2 and 3), so a publisher on ``/rosout`` or ``/parameter_events`` whose process no longer
runs is a ghost's. A container stopped by a signal it handles leaves none (its participant says goodbye).
"""
from __future__ import annotations

import contextlib
import os
import threading
import time
from typing import Any, Iterator

import rclpy
from rclpy.context import Context
from rclpy.node import Node

_lock = threading.Lock()
_anchor: Node | None = None
_client_anchor: Node | None = None
#: Topics every rclpy node publishes on: their publishers name every participant with a node.
_EVERY_NODES_TOPICS = ("/rosout", "/parameter_events")


def process_context() -> Context:
    """rclpy's default context, initialized on first use and kept, with its participant, until the process ends."""
    global _anchor
    with _lock:
        context = rclpy.get_default_context()
        if not context.ok():
            rclpy.init(context=context)
            _anchor = None
        if _anchor is None:
            _anchor = Node("ipc_testing_process_anchor", context=context)
        return context


@contextlib.contextmanager
def client_context() -> Iterator[Context]:
    """The context for a test's clients of container processes: the last test's, unless that one left a ghost in
    its graph (then a new one); its participant is held by an anchor node."""
    global _client_anchor
    if _client_anchor is None or not _client_anchor.context.ok():
        context = Context()
        rclpy.init(context=context)
        _client_anchor = Node("ipc_testing_client_anchor", context=context)
    anchor = _client_anchor
    try:
        yield anchor.context
    finally:
        if ghost_processes(anchor, wait=0.3):
            _client_anchor = None
            anchor.destroy_node()
            rclpy.try_shutdown(context=anchor.context)


def process_id(info: Any) -> int:
    """The low 16 bits of the process id of the participant of an endpoint (``TopicEndpointInfo``): bytes 4-5 of its
    GUID prefix, little-endian, on Fast DDS 2 and 3."""
    return int.from_bytes(bytes(info.endpoint_gid)[4:6], "little")


def ghost_processes(node: Node, wait: float) -> set[int]:
    """The process ids (low 16 bits) of participants in ``node``'s graph whose process no longer runs, after
    waiting up to ``wait`` s for them to leave (a container that was just stopped cleanly is on its way out)."""
    deadline = time.monotonic() + wait
    while True:
        named = {process_id(info) for topic in _EVERY_NODES_TOPICS for info in node.get_publishers_info_by_topic(topic)}
        running = {int(name) & 0xFFFF for name in os.listdir("/proc") if name.isdigit()}
        if not named - running or time.monotonic() >= deadline:
            return named - running
        time.sleep(0.05)
