"""Test-session isolation: every run gets its own ROS domain and never leaves loopback.

The variables are set at import time, before any test imports rclpy, so in-process nodes and the container
processes the tests start (which inherit the environment) all share the one private domain.
"""
from __future__ import annotations

import faulthandler
import fcntl
import os
import random
from typing import Generator, Iterator

import pytest

#: One random base per test run, chosen by the process pytest-xdist's workers inherit it from; each worker (gw0,
#: gw1, ...) adds its index, so that parallel workers never see each other's containers. IPC_TEST_DOMAIN_ID
#: fixes the base (to replay a run).
os.environ.setdefault("IPC_TEST_DOMAIN_BASE", os.environ.get("IPC_TEST_DOMAIN_ID") or str(random.randint(1, 160)))
_WORKER = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
os.environ["ROS_DOMAIN_ID"] = str(int(os.environ["IPC_TEST_DOMAIN_BASE"]) + _WORKER)
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.pop("ROS_STATIC_PEERS", None)

# rclpy and the helpers are imported only now, after the domain is set.
from rclpy.node import Node  # noqa: E402

from component_container.discovery_profile import use_fastdds_profile  # noqa: E402

# The tests' shared participant lives as long as the worker (ipc_testing.process_context), so it is not the newcomer
# that announces itself to each container a test starts: the container is, and it may miss the participant's
# answer (Fast DDS 2.14 drops it before it listens) and then find the tests' client only at the participant's
# next announcement, 3 s later by Fast DDS's default. The container's profile re-announces every 0.25 s, as the
# command line's does. Set before the process's first participant; the processes the tests start inherit it.
use_fastdds_profile()

from container_process import Containers, SharedContainer  # noqa: E402
from ipc_testing.process_context import client_context, process_context  # noqa: E402
from installed import REPO, InstalledEnv, build_wheel, clean_copy, make_env, seed_interfaces  # noqa: E402


#: Seconds past pytest-timeout's limit (``timeout`` in pyproject.toml) after which a test's process is ended.
HARD_TIMEOUT_MARGIN = 60.0
_stderr = pytest.StashKey[int]()


def pytest_configure(config: pytest.Config) -> None:
    config.stash[_stderr] = os.dup(2)  # the terminal, not a test's captured output (capture is suspended here)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item) -> Generator[None, None, None]:
    """pytest-timeout fails a test that overruns by raising in its main thread, which cannot happen while that
    thread is stuck in C code that holds the GIL (a deadlock inside rclpy or the middleware). faulthandler's
    watchdog is a C thread: it prints every thread's stack to the terminal and ends the process, and
    pytest-xdist reports the test as crashing its worker and goes on with a new one."""
    limit = float(item.config.getini("timeout") or 0)
    if limit > 0:
        faulthandler.dump_traceback_later(limit + HARD_TIMEOUT_MARGIN, exit=True, file=item.config.stash[_stderr])
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests marked ``long`` first, the rest in their order: pytest-xdist hands tests out in this order, so the
    long ones start while the short ones fill the other workers, rather than one of them keeping a worker busy
    after all the others have finished. Only tests with fixtures of their own are marked (a module fixture
    would be set up again on the worker that runs the rest of its module)."""
    items.sort(key=lambda item: item.get_closest_marker("long") is None)


@pytest.fixture(scope="session")
def ros() -> None:
    """The default context, the process's one (ipc_testing.process_context): ContainerClient and rclpy.spin_once
    use the global executor."""
    process_context()


@pytest.fixture()
def probe(ros: None) -> Iterator[Node]:
    """A client node of the containers a test starts, in the clients' context (client_context: kept from test to
    test until one leaves a ghost); spun by rclpy's global executor (of the default context) where a helper calls
    rclpy.spin_once. Without parameter services: nobody sets its parameters, and its seven services made creating
    and destroying it (once per test) cost three times the CPU (11 ms instead of 4)."""
    with client_context() as context:
        node = Node("container_test_probe", context=context, start_parameter_services=False)
        yield node
        node.destroy_node()



@pytest.fixture()
def containers(probe: Node) -> Iterator[Containers]:
    started = Containers(probe)
    try:
        yield started
    finally:
        started.close()


@pytest.fixture(scope="session")
def installed_env(tmp_path_factory: pytest.TempPathFactory, worker_id: str) -> InstalledEnv:
    """The project's wheel, built once per test run from a clean copy of the tree and installed non-editable
    into an environment of its own (see tests/installed.py), reusing the interfaces the editable install
    compiled when their inputs are the same. With pytest-xdist the first worker to ask builds it under a lock;
    the others reuse it."""
    shared = tmp_path_factory.getbasetemp() if worker_id == "master" else tmp_path_factory.getbasetemp().parent
    root = shared / "installed"
    with open(shared / "installed.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / "ready").exists():
            root.mkdir(exist_ok=True)
            source = clean_copy(REPO, root / "src")
            seed_interfaces(REPO, source)
            wheel = build_wheel(source, root / "wheels")
            env = make_env(root / "env")
            env.install(wheel)
            (root / "ready").write_text(wheel.name)
    return InstalledEnv(root / "env")


@pytest.fixture
def shared(shared_container: SharedContainer, probe: Node) -> Iterator[SharedContainer]:
    """The module's ``shared_container`` (each module defines that fixture, with its configurations), checked
    alive before the test and alive and empty after it."""
    assert shared_container.process.alive(), shared_container.process.output[-3000:]
    yield shared_container
    shared_container.check()
