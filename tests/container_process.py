"""Start a real container process the way a user would, and always stop it by its pid."""
from __future__ import annotations

import contextlib
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import time
from typing import Any, Callable, Iterator

from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from rclpy.executors import SingleThreadedExecutor
import rclpy
from rclpy.node import Node
from std_msgs.msg import String

from component_container.parameter_values import parameter_msg

REPO = pathlib.Path(__file__).resolve().parents[1]


class ContainerProcess:
    """``python -m component_container`` as a subprocess; a context manager that stops it on exit.

    Its output goes to a temporary file, not a pipe: a pipe nobody reads while the test runs fills up (64 KiB
    of log lines) and then blocks the container inside its logging calls.
    """

    def __init__(self, *args: str, name: str = "ComponentManager", cwd: str | None = None) -> None:
        self.name = name if name.startswith("/") else f"/{name}"
        command = [sys.executable, "-m", "component_container", *args]
        if name != "ComponentManager":
            command += ["--ros-args", "-r", f"__node:={self.name.rsplit('/', 1)[1]}"]
        self._log = tempfile.TemporaryFile(mode="w+", prefix="container_", suffix=".log")
        self.process = subprocess.Popen(command, stdout=self._log, stderr=subprocess.STDOUT,
                                        text=True, cwd=cwd, env=dict(os.environ))

    @property
    def pid(self) -> int:
        return self.process.pid

    @property
    def output(self) -> str:
        """Everything the container printed so far."""
        self._log.seek(0)
        return self._log.read()

    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> int:
        """Signal the container and wait; kill it if it does not exit in time. Returns the exit code."""
        if self.alive():
            self.process.send_signal(sig)
            try:
                self.process.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
                raise AssertionError(f"container {self.pid} did not exit within {timeout} s:\n{self.output}")
        return self.process.returncode

    def __enter__(self) -> "ContainerProcess":
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.alive():
            self.process.kill()
            self.process.wait()


class ContainerClient:
    """A plain rclpy client of a container's three services."""

    def __init__(self, node: Node, container: str = "/ComponentManager") -> None:
        self.node = node
        self._load = node.create_client(LoadNode, f"{container}/_container/load_node")
        self._unload = node.create_client(UnloadNode, f"{container}/_container/unload_node")
        self._list = node.create_client(ListNodes, f"{container}/_container/list_nodes")

    def wait(self, timeout: float = 20.0) -> None:
        """Wait until the three services are discovered *and* replies come back.

        ``wait_for_service`` returns once this side has matched the service's endpoints; the container may
        not have matched this client's reply reader yet, and Fast DDS then drops the reply ("failed to send
        response (timeout)") and the caller waits forever, the race launch_ros and ``ros2 component`` users
        hit too. So each service is called with a harmless request until it answers once: ListNodes,
        UnloadNode of id 0 (never allocated) and a LoadNode of an empty package name (refused before an id
        is allocated).
        """
        deadline = time.monotonic() + timeout
        for client in (self._load, self._unload, self._list):
            if not client.wait_for_service(timeout_sec=max(0.1, deadline - time.monotonic())):
                raise AssertionError(f"service {client.srv_name} did not appear within {timeout} s")
        for client, request in ((self._list, ListNodes.Request()), (self._unload, UnloadNode.Request()),
                                (self._load, LoadNode.Request())):
            while True:
                try:
                    self._call(client, request, timeout=1.0)
                    break
                except AssertionError:
                    if time.monotonic() > deadline:
                        raise

    def _call(self, client: Any, request: Any, timeout: float = 20.0) -> Any:
        future = client.call_async(request)
        executor = SingleThreadedExecutor(context=self.node.context)
        executor.add_node(self.node)
        executor.spin_until_future_complete(future, timeout_sec=timeout)
        executor.remove_node(self.node)
        executor.shutdown()  # else its finalizer runs after rclpy's shutdown and prints InvalidHandle at exit
        if not future.done():
            raise AssertionError(f"no reply from {client.srv_name} within {timeout} s")
        return future.result()

    def load(self, plugin: str, package: str = "components", *, name: str = "", namespace: str = "",
             parameters: dict[str, Any] | None = None, extra: dict[str, Any] | None = None,
             remaps: list[str] | None = None, log_level: int = 0) -> LoadNode.Response:
        request = LoadNode.Request(
            package_name=package, plugin_name=plugin, node_name=name, node_namespace=namespace,
            log_level=log_level, remap_rules=remaps or [],
            parameters=[parameter_msg(k, v) for k, v in (parameters or {}).items()],
            extra_arguments=[parameter_msg(k, v) for k, v in (extra or {}).items()])
        return self._call(self._load, request)

    def unload(self, unique_id: int) -> UnloadNode.Response:
        return self._call(self._unload, UnloadNode.Request(unique_id=unique_id))

    def list(self) -> ListNodes.Response:
        return self._call(self._list, ListNodes.Request())


def call_until_answered(node: Node, client: Any, request: Any, timeout: float = 20.0) -> Any:
    """Call a service (already discovered) and return its response, asking again every second until it
    answers: Fast DDS drops a reply to a client it has not matched yet. Only for idempotent calls."""
    deadline = time.monotonic() + timeout
    while True:
        future = client.call_async(request)
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
        executor.spin_until_future_complete(future, timeout_sec=1.0)
        executor.remove_node(node)
        executor.shutdown()  # as in ContainerClient._call
        if future.done():
            return future.result()
        client.remove_pending_request(future)
        if time.monotonic() > deadline:
            raise TimeoutError(f"no reply from {client.srv_name} within {timeout:g} s")


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



def wait_until(predicate: Callable[[], Any], timeout: float, node: Node | None = None) -> Any:
    """Poll ``predicate`` (spinning ``node`` meanwhile, if given) until it is truthy or ``timeout`` passes."""
    deadline = time.monotonic() + timeout
    while True:
        result = predicate()
        if result or time.monotonic() > deadline:
            return result
        if node is not None:
            rclpy.spin_once(node, timeout_sec=0.02)
        else:
            time.sleep(0.02)



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
