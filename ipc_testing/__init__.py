"""One harness for starting containers and calling them, shared by the tests and the benchmarks (the role of
rosbag2's ``rosbag2_test_common``).

* :class:`~ipc_testing.process.ContainerProcess`: ``python -m component_container`` as a subprocess, its output
  in a file, always stopped by its pid;
* :class:`~ipc_testing.client.ContainerClient`: a plain rclpy client of a container's LoadNode / UnloadNode /
  ListNodes services;
* :mod:`~ipc_testing.calls`: one service call (optionally sent again until answered), and waiting on a condition
  while spinning;
* :func:`~ipc_testing.in_process.in_process_manager`: a container's manager in the test process;
* :func:`~ipc_testing.process_context.process_context`: the test process's one rclpy context, which no test shuts
  down (Fast DDS 2.14 can livelock destroying a participant);
* :mod:`~ipc_testing.foxglove_client`: Foxglove's own WebSocket client (node, from a checkout's
  tests/foxglove_client), driven over its stdin and stdout.

Nothing in the product imports it (``tests/test_layout.py``).
"""
from ipc_testing.calls import call, spin_for, wait_until
from ipc_testing.client import ContainerClient
from ipc_testing.in_process import in_process_manager
from ipc_testing.process import ContainerProcess, stop_process

__all__ = ["ContainerClient", "ContainerProcess", "call", "in_process_manager", "spin_for", "stop_process", "wait_until"]
