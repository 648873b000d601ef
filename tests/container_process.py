"""Helpers of the container tests, over the shared harness (ipc_testing): containers started the way a user
starts them and always stopped by their pid."""
from __future__ import annotations

import contextlib
import json
import os
import pathlib
import subprocess
from typing import Any, Iterator

from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ipc_testing import ContainerClient, ContainerProcess, call, wait_until  # noqa: F401 - shared by the tests
from ipc_testing.process_context import process_id, running_process_ids

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


def rosout_writers(node: Node) -> set[tuple[str, int, bool]]:
    """Every node in ``node``'s graph with a /rosout publisher: its name, its process id (low 16 bits, from its
    participant's GUID) and whether that process runs (False: a ghost)."""
    running = running_process_ids()
    return {(info.node_name, process_id(info), process_id(info) in running)
            for info in node.get_publishers_info_by_topic("/rosout")}



class Received:
    """A plain rclpy subscription of std_msgs/String that records what arrives."""

    def __init__(self, node: Node, topic: str) -> None:
        self.messages: list[str] = []
        self.subscription = node.create_subscription(
            String, topic, lambda message: self.messages.append(message.data), 10)



def unload_all(client: ContainerClient) -> None:
    for unique_id, _name in listing(client):
        assert client.unload(unique_id).success, unique_id


def listing(client: ContainerClient) -> list[tuple[int, str]]:
    response = client.list()
    return list(zip(response.unique_ids, response.full_node_names))



class Containers:
    """Starts containers (repository root as cwd) and guarantees they are stopped and gone afterwards."""

    def __init__(self, probe: Node) -> None:
        self.probe = probe
        self.started: list[ContainerProcess] = []

    def start(self, *args: str, container: str = "/ComponentManager", wait: bool = True,
              env: dict[str, str] | None = None) -> tuple[ContainerProcess, ContainerClient]:
        process = ContainerProcess(*args, cwd=str(REPO), env=env)
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


class SharedContainer:
    """One container shared by the tests of a module (a module-scoped fixture), under a name of its own, with a
    client on a node of its own.

    :meth:`check` runs after every test: the container is alive and ListNodes answers with nothing loaded (what a
    test left is unloaded first, so that the next test starts clean, and the test is reported). :meth:`close`
    stops it: it must exit 0. A test that reads the container's log takes ``mark = shared.mark()`` first and
    reads ``shared.output_since(mark)``.
    """

    def __init__(self, *args: str, name: str) -> None:
        self.node = Node(f"{name}_client")
        self.process = ContainerProcess(*args, name=name, cwd=str(REPO))
        self.client = ContainerClient(self.node, self.process.name)
        try:
            self.client.wait(timeout=30.0)
        except AssertionError:
            self.process.stop(check=False)
            raise AssertionError(f"container {self.process.name} did not come up:\n{self.process.output}") from None

    def mark(self) -> int:
        return len(self.process.output)

    def output_since(self, mark: int) -> str:
        return self.process.output[mark:]

    def check(self) -> None:
        assert self.process.alive(), (f"shared container {self.process.name} died (exit code "
                                      f"{self.process.process.poll()}):\n{self.process.output[-3000:]}")
        left = self.client.listing()
        for unique_id, _name in left:
            self.client.unload(unique_id)
        assert left == [], f"the test left components loaded in {self.process.name}: {left}"

    def close(self) -> None:
        with self.process:
            status = self.process.stop() if self.process.alive() else self.process.returncode
        self.client.destroy()
        self.node.destroy_node()
        print(f"--- output of shared container {self.process.name} ({self.process.pid}, exit code {status}):\n"
              f"{self.process.output}")
        assert status == 0, f"shared container {self.process.name} exited with {status}"
        assert not pid_alive(self.process.pid)


def recorder_stats(node: Node, recorder: str) -> dict[str, Any]:
    """The live counts a recorder's ``~/get_stats`` answers (JSON), called until it answers."""
    client = node.create_client(Trigger, f"{recorder}/get_stats")
    try:
        return json.loads(call(node, client, Trigger.Request(), again=True).message)
    finally:
        node.destroy_client(client)


def written(node: Node, recorder: str, topic: str) -> int:
    """Messages of ``topic`` the recorder has written to its current bag."""
    return recorder_stats(node, recorder)["current"]["topics"].get(topic, {}).get("written", 0)


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
            _unmount(directory)


@contextlib.contextmanager
def read_only_view(source: pathlib.Path, directory: pathlib.Path) -> Iterator[tuple[pathlib.Path | None, str]]:
    """``source`` seen through a read-only bind mount at ``directory``: yields (``directory``, "") if this
    process may mount one, else (None, why not)."""
    directory.mkdir()
    if os.geteuid() != 0:
        yield None, "a bind mount needs root (the tests run as root in CI)"
        return
    bind = subprocess.run(["mount", "--bind", str(source), str(directory)], capture_output=True, text=True)
    if bind.returncode != 0:
        yield None, f"mount --bind failed: {bind.stderr.strip()}"
        return
    try:
        remount = subprocess.run(["mount", "-o", "remount,bind,ro", str(directory)], capture_output=True, text=True)
        if remount.returncode != 0:
            yield None, f"mount -o remount,bind,ro failed: {remount.stderr.strip()}"
            return
        assert os.statvfs(directory).f_flag & os.ST_RDONLY, f"{directory} is not read-only"
        yield directory, ""
    finally:
        _unmount(directory)


def _unmount(directory: pathlib.Path) -> None:
    """Unmount ``directory``, lazily if it is still busy."""
    if subprocess.run(["umount", str(directory)], capture_output=True).returncode != 0:
        subprocess.run(["umount", "-l", str(directory)], capture_output=True)
