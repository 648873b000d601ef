"""The harness's clients' context: a participant whose process is gone without saying goodbye (SIGKILL) is seen
as a ghost, one that shut down cleanly is not, so the clients' context is replaced only after the former."""
from __future__ import annotations

import signal
import subprocess
import sys

import pytest
from rclpy.node import Node

from ipc_testing import wait_until
from ipc_testing.process_context import ghost_processes, process_context

#: A ROS process with one node, until a signal: rclpy's own handler shuts its context down on SIGINT.
NODE = ("import rclpy, sys; from rclpy.node import Node; rclpy.init(); node = Node('ghost_check_' + sys.argv[1]); "
        "print('ready', flush=True)\ntry:\n    rclpy.spin(node)\nexcept BaseException:\n    pass\n"
        "node.destroy_node(); rclpy.try_shutdown()")


@pytest.fixture()
def observer() -> Node:
    node = Node("ghost_observer", context=process_context())
    yield node
    node.destroy_node()


@pytest.mark.parametrize(("stop", "ghost"), [(signal.SIGKILL, True), (signal.SIGINT, False)])
def test_a_participant_gone_without_goodbye_is_a_ghost(observer: Node, stop: signal.Signals, ghost: bool) -> None:
    process = subprocess.Popen([sys.executable, "-c", NODE, stop.name.lower()], stdout=subprocess.PIPE, text=True)
    try:
        assert process.stdout is not None and process.stdout.readline() == "ready\n"
        name = f"ghost_check_{stop.name.lower()}"
        assert wait_until(lambda: name in observer.get_node_names(), 20.0), observer.get_node_names()
        process.send_signal(stop)
        process.wait(20)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    if ghost:
        assert process.pid & 0xFFFF in ghost_processes(observer, wait=0.3)
    else:
        assert wait_until(lambda: process.pid & 0xFFFF not in ghost_processes(observer, wait=0.0), 5.0)
