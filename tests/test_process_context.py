"""The harness's clients' contexts: a participant whose process is gone without saying goodbye (SIGKILL) is seen
as a ghost, one that shut down cleanly is not; a clients' context with a ghost is set aside, never destroyed."""
from __future__ import annotations

import signal
import subprocess
import sys

import pytest
from rclpy.node import Node

from ipc_testing import wait_until
from ipc_testing.process_context import client_context, ghost_processes, process_context

#: A ROS process with one node, until a signal: rclpy's own handler shuts its context down on SIGINT.
NODE = ("import rclpy, sys; from rclpy.node import Node; rclpy.init(); node = Node('ghost_check_' + sys.argv[1]); "
        "print('ready', flush=True)\ntry:\n    rclpy.spin(node)\nexcept BaseException:\n    pass\n"
        "node.destroy_node(); rclpy.try_shutdown()")


def start_node(name: str) -> subprocess.Popen:
    process = subprocess.Popen([sys.executable, "-c", NODE, name], stdout=subprocess.PIPE, text=True)
    assert process.stdout is not None and process.stdout.readline() == "ready\n"
    return process


def stop_node(process: subprocess.Popen, stop: signal.Signals) -> None:
    if process.poll() is None:
        process.send_signal(stop)
        try:
            process.wait(20)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()


@pytest.fixture()
def observer() -> Node:
    node = Node("ghost_observer", context=process_context())
    yield node
    node.destroy_node()


@pytest.mark.parametrize(("stop", "ghost"), [(signal.SIGKILL, True), (signal.SIGINT, False)])
def test_a_participant_gone_without_goodbye_is_a_ghost(observer: Node, stop: signal.Signals, ghost: bool) -> None:
    process = start_node(stop.name.lower())
    try:
        name = f"ghost_check_{stop.name.lower()}"
        assert wait_until(lambda: name in observer.get_node_names(), 20.0), observer.get_node_names()
    finally:
        stop_node(process, stop)
    if ghost:
        assert process.pid & 0xFFFF in ghost_processes(observer, wait=0.3)
    else:
        assert wait_until(lambda: process.pid & 0xFFFF not in ghost_processes(observer, wait=0.0), 5.0)


def test_a_clients_context_with_a_ghost_is_set_aside_and_kept() -> None:
    """Destroying a participant while discovery goes on can hang (Fast DDS 2.14) or crash (Fast DDS 3.2) the
    process, so the context that saw a container killed is not shut down: the next test gets another one."""
    with client_context() as context:
        observer = Node("ghost_observer", context=context)
        process = start_node("killed")
        try:
            assert wait_until(lambda: "ghost_check_killed" in observer.get_node_names(), 20.0)
        finally:
            stop_node(process, signal.SIGKILL)
            observer.destroy_node()
    with client_context() as other:
        assert other is not context
        assert context.ok()
