"""Start a real container process the way a user would, and always stop it by its pid."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from typing import Any

from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from component_container.parameter_values import parameter_msg


class ContainerProcess:
    """``python -m component_container`` as a subprocess; a context manager that stops it on exit."""

    def __init__(self, *args: str, name: str = "ComponentManager", cwd: str | None = None) -> None:
        self.name = name if name.startswith("/") else f"/{name}"
        command = [sys.executable, "-m", "component_container", *args]
        if name != "ComponentManager":
            command += ["--ros-args", "-r", f"__node:={self.name.rsplit('/', 1)[1]}"]
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        text=True, cwd=cwd, env=dict(os.environ))
        self.output = ""

    @property
    def pid(self) -> int:
        return self.process.pid

    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> int:
        """Signal the container and wait; kill it if it does not exit in time. Returns the exit code."""
        if self.alive():
            self.process.send_signal(sig)
            try:
                self.output, _ = self.process.communicate(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.output, _ = self.process.communicate()
                raise AssertionError(f"container {self.pid} did not exit within {timeout} s:\n{self.output}")
        elif not self.output and self.process.stdout is not None:
            self.output = self.process.stdout.read()
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
