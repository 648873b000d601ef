"""The rclpy contexts of a test process, whose Fast DDS participants live as long as the process.

Why: every rclpy context is a Fast DDS participant, destroyed with the context's last node, and destroying one is
not safe while discovery goes on. Fast DDS 2.14 (Jazzy's wheels) can livelock:
``DomainParticipant::set_listener(nullptr)`` waits for the participant's discovery callbacks in flight by spinning
on a condition variable's ``wait_until`` whose deadline never blocks, re-taking the listener mutex at once each
time; a discovery callback that has begun needs that mutex to finish, so it never gets it, and the destroying
thread spins on (with the GIL held, the whole process stops). A test run that made a context per test destroyed
about 350 participants in its workers, and two of about twenty runs hung (docs/limitations.md, Platform, has the
stacks). Fast DDS 3.2 (Kilted's wheels) crashed instead: a worker's segmentation fault in rclpy's
``Node.destroy_node`` of a context's last node, once in twelve runs that destroyed about fifteen participants each.
So the contexts here are made on first use and held by an anchor node until the process ends (pytest-xdist ends
a worker that does not exit within 10 s of its last test); nodes come and go. (The tests of the DDS path between
two participants of one process still make the second one per test: a peer kept across tests once lost the
process's participant for good in a worker, both of its next tests failing to match.)

* :func:`process_context`: rclpy's default context, for every in-process node that needs no other participant.
* :func:`kept_context`: another context of the process, on another domain if asked.
* :func:`client_context`: the clients of container processes. A participant that outlives a SIGKILLed container
  keeps it as a ghost until the container's lease ends (20 s by Fast DDS's default), and meanwhile finds a
  container started after it about 3 s late instead of 0.5 s; once the ghost is gone it finds one as fast as a new
  participant would. So the clients have a pool of contexts: a test gets the first one whose graph holds no ghost,
  and a new one only when each does (a few per worker while tests that kill containers follow one another).
  A participant's GUID prefix holds its process id (bytes 4-5, little-endian, the low 16 bits: Fast DDS 2 and 3),
  so a publisher on ``/rosout`` or ``/parameter_events`` whose process no longer runs is a ghost's. A container
  stopped by a signal it handles leaves none (its participant says goodbye).
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
#: The anchor node of each kept context, by its name.
_anchors: dict[str, Node] = {}
#: The anchors of the clients' contexts, oldest first.
_clients: list[Node] = []
#: Topics every rclpy node publishes on: their publishers name every participant with a node.
_EVERY_NODES_TOPICS = ("/rosout", "/parameter_events")


def _anchored(name: str, context: Context, **init: Any) -> Node:
    """An anchor node holding ``context``'s participant (initializing the context first if it is not)."""
    if not context.ok():
        rclpy.init(context=context, **init)
    return Node(name, context=context, start_parameter_services=False)


def kept_context(name: str, domain_id: int | None = None) -> Context:
    """A context of its own for this process (on ``domain_id``, the environment's by default), made on the first
    call with ``name`` and kept, with its participant, until the process ends."""
    with _lock:
        if name not in _anchors:
            _anchors[name] = _anchored(f"ipc_testing_{name}_anchor", Context(), domain_id=domain_id)
        return _anchors[name].context


def process_context() -> Context:
    """rclpy's default context, initialized on first use and kept, with its participant, until the process ends."""
    with _lock:
        context = rclpy.get_default_context()
        if "process" not in _anchors or not context.ok():
            _anchors["process"] = _anchored("ipc_testing_process_anchor", context)
        return context


@contextlib.contextmanager
def client_context() -> Iterator[Context]:
    """The context for a test's clients of container processes: the first of the clients' contexts whose graph
    holds no ghost, or a new one."""
    anchor = next((client for client in _clients if not ghost_processes(client, wait=0.0)), None)
    if anchor is None:
        anchor = _anchored(f"ipc_testing_client_anchor_{len(_clients)}", Context())
        _clients.append(anchor)
    try:
        yield anchor.context
    finally:
        ghost_processes(anchor, wait=0.3)  # a container the test stopped cleanly leaves before the next test looks


def process_id(info: Any) -> int:
    """The low 16 bits of the process id of the participant of an endpoint (``TopicEndpointInfo``): bytes 4-5 of its
    GUID prefix, little-endian, on Fast DDS 2 and 3."""
    return int.from_bytes(bytes(info.endpoint_gid)[4:6], "little")


def running_process_ids() -> set[int]:
    """The low 16 bits of the ids of the processes that run now, to compare with :func:`process_id`."""
    return {int(name) & 0xFFFF for name in os.listdir("/proc") if name.isdigit()}


def ghost_processes(node: Node, wait: float) -> set[int]:
    """The process ids (low 16 bits) of participants in ``node``'s graph whose process no longer runs, after
    waiting up to ``wait`` s for them to leave (a container that was just stopped cleanly is on its way out)."""
    deadline = time.monotonic() + wait
    while True:
        named = {process_id(info) for topic in _EVERY_NODES_TOPICS for info in node.get_publishers_info_by_topic(topic)}
        running = running_process_ids()
        if not named - running or time.monotonic() >= deadline:
            return named - running
        time.sleep(0.05)
