"""Writing your own components, end to end (docs/writing-components.md): the example package and a package made
by ``ipc-component create``, each pip-installed (non-editable, ``--no-deps``) into the environment that holds
the project's wheel (tests/installed.py), listed by the installed ``ipc-component types``, loaded by plugin name
into a container started from that environment and unloaded without leaving anything behind.

Nothing is installed into the test venv: its ``ipc-component types`` output is checked exactly elsewhere.
"""
from __future__ import annotations

import collections
import contextlib
import os
import re
import secrets
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from component_container.component_node import REUSE_WATCH
from component_container.parameter_values import parameter_msg
from installed import REPO, InstalledEnv

EXAMPLE = REPO / "examples" / "rclpy_components_example"
PACKAGE = "rclpy_components_example"
PUBLISHER = f"{PACKAGE}::CounterPublisher"
LISTENER = f"{PACKAGE}::ZeroCopyListener"
#: What CounterPublisher publishes: "<prefix> <n> @<id of the message object, hex>".
MESSAGE = re.compile(r"^(?P<prefix>\S+) (?P<n>\d+) @(?P<id>[0-9a-f]+)$")
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


# --- helpers ----------------------------------------------------------------------------------------------
def wait_for(predicate: Callable[[], Any], timeout: float, node: Node) -> Any:
    """Spin ``node`` until ``predicate()`` is truthy or ``timeout`` s passed; its last value."""
    deadline = time.monotonic() + timeout
    while True:
        result = predicate()
        if result or time.monotonic() > deadline:
            return result
        rclpy.spin_once(node, timeout_sec=0.05)


def call_until_answered(node: Node, client: Any, request: Any, timeout: float = 20.0) -> Any:
    """An idempotent service call, sent again every second until answered: Fast DDS drops a reply to a client
    whose reader the server has not matched yet."""
    assert client.wait_for_service(timeout_sec=timeout), f"{client.srv_name} not found"
    deadline = time.monotonic() + timeout
    while True:
        future = client.call_async(request)
        rclpy.spin_until_future_complete(node, future, timeout_sec=1.0)
        if future.done():
            return future.result()
        client.remove_pending_request(future)
        assert time.monotonic() < deadline, f"no reply from {client.srv_name} within {timeout:g} s"


def threads(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("Threads:"):
            return int(line.split()[1])
    raise AssertionError(f"no Threads: line for {pid}")


def thread_names(pid: int) -> collections.Counter[str]:
    """The process's threads by name (for the message of a failed thread-count check)."""
    names: collections.Counter[str] = collections.Counter()
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            names[(task / "comm").read_text().strip()] += 1
    return names


@contextlib.contextmanager
def container(env: InstalledEnv, name: str, *args: str) -> Iterator[subprocess.Popen]:
    """``python -m component_container`` of the installed environment, always stopped by its pid; its output
    goes to a file (a pipe nobody reads would fill up and block it) and is shown if the test fails."""
    with tempfile.TemporaryFile("w+") as log:
        process = subprocess.Popen([str(env.python), "-m", "component_container", *args, "--ros-args", "-r",
                                    f"__node:={name}"], cwd=env.root, env=env.env(), stdout=log,
                                   stderr=subprocess.STDOUT, text=True)
        try:
            yield process
        except BaseException:
            log.seek(0)
            print(f"--- container {name} output ---\n{log.read()}")
            raise
        finally:
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
                try:
                    process.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
        log.seek(0)
        process.output = log.read()  # type: ignore[attr-defined]


def cli(env: InstalledEnv, *args: str) -> subprocess.CompletedProcess:
    return env.run(env.script("ipc-component"), *args)


def load(env: InstalledEnv, container_name: str, package: str, plugin: str, *args: str) -> int:
    """Load through the installed ``ipc-component load -q``; the unique id."""
    loaded = cli(env, "load", f"/{container_name}", package, plugin, "-q", *args)
    assert loaded.returncode == 0, (plugin, loaded.stdout, loaded.stderr)
    return int(loaded.stdout.split()[0])


def wait_until_serving(env: InstalledEnv, name: str, timeout: float = 30.0) -> None:
    """Until the container answers ``ipc-component list``: its services run (on a thread started after its
    node appears in the graph)."""
    deadline = time.monotonic() + timeout
    while (listed := cli(env, "list", f"/{name}")).returncode != 0:
        assert time.monotonic() < deadline, f"/{name} did not answer: {listed.stderr}"


class Statuses:
    """The latest /diagnostics values per status name."""

    def __init__(self, node: Node) -> None:
        self.latest: dict[str, dict[str, str]] = {}
        self.subscription = node.create_subscription(DiagnosticArray, "/diagnostics", self._on_array, 10)

    def _on_array(self, array: DiagnosticArray) -> None:
        for status in array.status:
            self.latest[status.name] = {kv.key: kv.value for kv in status.values}

    def of(self, full_node_name: str) -> dict[str, str]:
        return next((values for name, values in self.latest.items() if name.endswith(f": {full_node_name}")), {})


# --- fixtures ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def example_env(installed_env: InstalledEnv, tmp_path_factory: pytest.TempPathFactory) -> InstalledEnv:
    """The installed environment with the example package installed as a user would (from a copy: pip builds
    in the source folder, and the work tree is not the test's to write in)."""
    source = shutil.copytree(EXAMPLE, tmp_path_factory.mktemp("example") / EXAMPLE.name,
                             ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    installed_env.install(source)
    return installed_env


# --- tests ------------------------------------------------------------------------------------------------
def test_the_example_is_installed_next_to_the_wheel_not_in_the_test_venv(example_env: InstalledEnv) -> None:
    found = example_env.run(example_env.python, "-c", f"import {PACKAGE}; print({PACKAGE}.__file__)")
    assert found.returncode == 0, found.stderr
    assert found.stdout.startswith(str(example_env.root)), found.stdout
    with pytest.raises(ImportError):
        __import__(PACKAGE)


def test_types_lists_the_example_plugins(example_env: InstalledEnv) -> None:
    every = cli(example_env, "types")
    assert every.returncode == 0, every.stderr
    assert f"{PACKAGE}\n  {PUBLISHER}\n  {LISTENER}\n" in every.stdout
    assert "components\n  components::CameraDriver" in every.stdout  # next to the project's own
    one = cli(example_env, "types", PACKAGE)
    assert (one.returncode, one.stdout) == (0, f"{PUBLISHER}\n{LISTENER}\n"), one.stderr


def test_example_components_zero_copy_dds_parameters_and_clean_unload(example_env: InstalledEnv,
                                                                      probe: Node) -> None:
    tag = f"ex{os.getpid()}_{secrets.token_hex(3)}"
    name, publisher, listener = f"{tag}_container", f"{tag}_publisher", f"{tag}_listener"
    topic = f"/{tag}/counter"
    received: list[str] = []
    probe.create_subscription(String, topic, lambda msg: received.append(msg.data), RELIABLE)
    statuses = Statuses(probe)
    set_parameters = probe.create_client(SetParameters, f"/{publisher}/set_parameters")
    ipc = ("-e", "use_intra_process_comms:=true", "-r", f"counter:={topic}")

    # The isolated executor gives each component a thread of its own: unloading must join both.
    with container(example_env, name, "--executor", "isolated") as process:
        wait_until_serving(example_env, name)
        before, before_names = threads(process.pid), thread_names(process.pid)
        # The listener first, so it also gets the publisher's first messages (copies, by the reuse rule).
        listener_id = load(example_env, name, PACKAGE, LISTENER, "-n", listener, *ipc)
        publisher_id = load(example_env, name, PACKAGE, PUBLISHER, "-n", publisher, "-p", "rate:=20.0", *ipc)
        assert threads(process.pid) >= before + 2

        # (b) a plain rclpy subscription in this process gets the messages over DDS.
        assert wait_for(lambda: len(received) >= 5, 20.0, probe), received
        assert all(MESSAGE.match(data) and data.startswith("count ") for data in received), received[:5]

        # (a) in the container, the listener got the very objects published (its /diagnostics status) ...
        def listener_status() -> dict[str, str]:
            return statuses.of(f"/{listener}")
        assert wait_for(lambda: int(listener_status().get("by_reference", 0)) >= 5, 20.0, probe), statuses.latest
        # The publisher's first messages arrive as copies (the reuse rule), and nothing twice: a message the
        # publisher also wrote to DDS never reaches the listener again through its DDS reader, even when the
        # listener's thread takes it while the publisher's thread is still writing it.
        assert int(listener_status()["copies"]) == REUSE_WATCH
        # ... with the same data that reached this process over DDS
        assert wait_for(lambda: listener_status()["last"] in received, 10.0, probe), (listener_status(), received)

        # (c) a dynamic parameter, set as `ros2 param set` does, changes what is published; a refused value
        # says why.
        result = call_until_answered(probe, set_parameters, SetParameters.Request(
            parameters=[parameter_msg("prefix", "changed")])).results[0]
        assert result.successful, result.reason
        assert wait_for(lambda: received[-1].startswith("changed "), 10.0, probe), received[-3:]
        assert wait_for(lambda: listener_status()["last"].startswith("changed "), 10.0, probe), listener_status()
        refused = call_until_answered(probe, set_parameters, SetParameters.Request(
            parameters=[parameter_msg("rate", 1000.0)])).results[0]
        assert not refused.successful and "rate" in refused.reason and "100" in refused.reason, refused.reason

        # (e) unloading leaves no node, endpoint or thread behind.
        unloaded = cli(example_env, "unload", f"/{name}", str(listener_id), str(publisher_id))
        assert unloaded.returncode == 0, unloaded.stderr

        def gone() -> bool:
            nodes = probe.get_node_names_and_namespaces()
            others = [i for i in probe.get_subscriptions_info_by_topic(topic) if i.node_name != probe.get_name()]
            return ((publisher, "/") not in nodes and (listener, "/") not in nodes and not others
                    and not probe.get_publishers_info_by_topic(topic))
        assert wait_for(gone, 10.0, probe), (probe.get_node_names_and_namespaces(),
                                             probe.get_publishers_info_by_topic(topic))
        assert wait_for(lambda: threads(process.pid) == before, 10.0, probe), \
            (threads(process.pid), before, thread_names(process.pid) - before_names,
             before_names - thread_names(process.pid))
        assert process.poll() is None
    assert process.returncode == 0, process.output
    assert re.search(r"\d+ received, \d+ by reference, \d+ copies", process.output), process.output  # destroyed


def test_a_created_package_installs_loads_and_unloads(example_env: InstalledEnv, probe: Node,
                                                      tmp_path: Path) -> None:
    created = cli(example_env, "create", "my_components", "--destination", str(tmp_path))
    assert created.returncode == 0, created.stderr
    root = tmp_path / "my_components"
    assert {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()} == {
        "pyproject.toml", "README.md", "my_components/__init__.py", "my_components/my_components.py"}
    again = cli(example_env, "create", "my_components", "--destination", str(tmp_path))
    assert again.returncode == 1 and "already exists" in again.stderr, (again.stdout, again.stderr)
    invalid = cli(example_env, "create", "My-Components", "--destination", str(tmp_path))
    assert invalid.returncode == 1 and "Invalid package name 'My-Components'" in invalid.stderr, invalid.stderr
    assert not (tmp_path / "My-Components").exists()

    example_env.install(root)
    types = cli(example_env, "types", "my_components")
    assert (types.returncode, types.stdout) == (0, "my_components::MyComponents\n"), types.stderr

    name = f"created{os.getpid()}_{secrets.token_hex(3)}"
    node = f"{name}_component"
    with container(example_env, name) as process:
        wait_until_serving(example_env, name)
        uid = load(example_env, name, "my_components", "my_components::MyComponents", "-n", node,
                   "-e", "use_intra_process_comms:=true")
        listed = cli(example_env, "list", f"/{name}")
        assert (listed.returncode, listed.stdout) == (0, f"{uid}  /{node}\n"), listed.stderr
        unloaded = cli(example_env, "unload", f"/{name}", str(uid))
        assert unloaded.returncode == 0, unloaded.stderr
        listed = cli(example_env, "list", f"/{name}")
        assert (listed.returncode, listed.stdout) == (0, ""), listed.stderr
        assert wait_for(lambda: (node, "/") not in probe.get_node_names_and_namespaces(), 10.0, probe)
    assert process.returncode == 0, process.output
