"""The one rclpy context of a test process, whose Fast DDS participant lives as long as the process.

Why: every rclpy context is a Fast DDS participant, destroyed with the context's last node. Fast DDS 2.14 (Jazzy's
wheels) can livelock destroying one: ``DomainParticipant::set_listener(nullptr)`` waits for the participant's
discovery callbacks in flight by spinning on a condition variable's ``wait_until`` whose deadline never blocks,
re-taking the listener mutex at once each time; a discovery callback that has begun needs that mutex to finish, so
it never gets it, and the destroying thread spins on (with the GIL held, the whole process stops). It takes a
discovery event arriving at the very moment of destruction, so it is rare per participant; a test run that made a
context per test destroyed about 350 participants in its workers and hung about one run in ten (the worker's
stacks are in docs/design/test-harness.md). Tests that share this context destroy none: nodes come and go, the
participant stays, held by an anchor node, until the process ends (pytest-xdist ends a worker that does not exit
within 10 s of its last test).

A test that needs a second participant in the process (the DDS path between two contexts) still makes a context
of its own; every other in-process node belongs here, and nothing shuts this context down.
"""
from __future__ import annotations

import threading

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
