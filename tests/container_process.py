"""Helpers of the container tests, over the shared harness (ipc_testing): containers started the way a user
starts them and always stopped by their pid."""
from __future__ import annotations

import contextlib
import os
import pathlib
import subprocess
from typing import Iterator

from rclpy.node import Node
from std_msgs.msg import String

from ipc_testing import ContainerClient, ContainerProcess, call, wait_until  # noqa: F401 - shared by the tests

REPO = pathlib.Path(__file__).resolve().parents[1]


# --- helpers of the container tests ---------------------------------------------------------------------
def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True



def proc_status(pid: int) -> dict[str, str]:
    fields = {}
    for line in pathlib.Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        fields[key] = value.strip()
    return fields



def node_names(node: Node) -> set[tuple[str, str]]:
    return set(node.get_node_names_and_namespaces())



class Received:
    """A plain rclpy subscription of std_msgs/String that records what arrives."""

    def __init__(self, node: Node, topic: str) -> None:
        self.messages: list[str] = []
        self.subscription = node.create_subscription(
            String, topic, lambda message: self.messages.append(message.data), 10)



def listing(client: ContainerClient) -> list[tuple[int, str]]:
    response = client.list()
    return list(zip(response.unique_ids, response.full_node_names))



class Containers:
    """Starts containers (repository root as cwd) and guarantees they are stopped and gone afterwards."""

    def __init__(self, probe: Node) -> None:
        self.probe = probe
        self.started: list[ContainerProcess] = []

    def start(self, *args: str, container: str = "/ComponentManager",
              wait: bool = True) -> tuple[ContainerProcess, ContainerClient]:
        process = ContainerProcess(*args, cwd=str(REPO))
        self.started.append(process)
        client = ContainerClient(self.probe, container)
        if wait:
            try:
                client.wait()
            except AssertionError:
                process.stop()
                raise AssertionError(f"container did not come up:\n{process.output}")
        return process, client

    def close(self) -> None:
        for process in self.started:
            with process:
                if process.alive():
                    process.stop()
            print(f"--- output of container {process.pid} (exit code {process.process.returncode}):\n"
                  f"{process.output}")  # shown by pytest when the test failed
            assert not process.alive() and not pid_alive(process.pid), f"container {process.pid} still runs"


@contextlib.contextmanager
def small_filesystem(directory: pathlib.Path, size: int) -> Iterator[bool]:
    """A tmpfs of ``size`` bytes at ``directory`` if this process may mount one (yields True), else False."""
    directory.mkdir()
    if os.environ.get("RECORDER_TEST_NO_TMPFS") or os.geteuid() != 0:
        yield False
        return
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(directory)],
                             capture_output=True).returncode == 0
    try:
        yield mounted
    finally:
        if mounted:
            if subprocess.run(["umount", str(directory)], capture_output=True).returncode != 0:
                subprocess.run(["umount", "-l", str(directory)], capture_output=True)
