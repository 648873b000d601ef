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

Except a test's client of container processes (:func:`client_context`): a participant that outlives a SIGKILLed
container keeps it as a ghost until its lease ends (20 s), and meanwhile finds a container started after it
about 2.5 s late (a participant kept across kills: 3.0 s from start to the first answered ListNodes; a new one:
0.55 s). The suite's tests kill containers in every worker; its clients are new each test, as before.
"""
from __future__ import annotations

import contextlib
import threading
from typing import Iterator

import rclpy
from rclpy.context import Context
from rclpy.node import Node

_lock = threading.Lock()
_anchor: Node | None = None


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
    """A context of the test's own, for the clients of the containers it starts; shut down after (its participant
    goes with its last node, which the caller destroys first)."""
    context = Context()
    rclpy.init(context=context)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)
