"""The component container as users run it: a real ``python -m component_container`` process, driven over
Fast DDS through its LoadNode / UnloadNode / ListNodes services by a plain rclpy node in the test process.

Containers run with the repository root as working directory, so that with ``--allow-module-plugins`` they can
import the helper components in tests/container_test_plugins.py as ``tests.container_test_plugins:<Class>``
(package name ``tests``). Every container a test starts is stopped by the test or its fixture, and the fixture
checks that its process is gone.
"""
from __future__ import annotations

import pathlib
import re
import signal
import time
from typing import Any, Callable, Iterator

import pytest
import rclpy
from rcl_interfaces.msg import Log, ParameterType
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from container_process import (
    REPO,
    ContainerClient,
    ContainerProcess,
    Containers,
    Received,
    listing,
    node_names,
    pid_alive,
    proc_status,
    wait_until,
)

PLUGINS = "tests.container_test_plugins"
TALKER, LISTENER = "components::Talker", "components::Listener"

UNKNOWN_PACKAGE = "Could not find requested resource in ament index"
UNKNOWN_PLUGIN = "Failed to find class with the requested plugin name."
CONSTRUCTOR = "Component constructor threw an exception: "


# --- helpers ----------------------------------------------------------------------------------------------
def get_parameter(node: Node, full_node_name: str, name: str) -> Any:
    """A component's parameter value read through its own parameter service, as ``ros2 param get`` does."""
    client = node.create_client(GetParameters, f"{full_node_name}/get_parameters")
    try:
        assert client.wait_for_service(timeout_sec=10.0), f"{full_node_name} has no parameter service"
        future = client.call_async(GetParameters.Request(names=[name]))
        rclpy.spin_until_future_complete(node, future, timeout_sec=10.0)
        assert future.done(), f"{full_node_name}/get_parameters did not answer"
        value = future.result().values[0]
    finally:
        node.destroy_client(client)
    return {ParameterType.PARAMETER_NOT_SET: None,
            ParameterType.PARAMETER_DOUBLE: value.double_value,
            ParameterType.PARAMETER_INTEGER: value.integer_value,
            ParameterType.PARAMETER_BOOL: value.bool_value,
            ParameterType.PARAMETER_STRING: value.string_value}[value.type]


def assert_failed(response: Any, message: str | None = None, *, prefix: str | None = None) -> None:
    assert not response.success, response
    if message is not None:
        assert response.error_message == message
    if prefix is not None:
        assert response.error_message.startswith(prefix), response.error_message
    assert response.full_node_name == "" and response.unique_id == 0


@pytest.fixture(scope="module", autouse=True)
def _ros(ros: None) -> None:
    """Every test here uses the default context (ContainerClient, rclpy.spin_once)."""


# --- load / list / unload -----------------------------------------------------------------------------------
def test_round_trips_and_unique_ids(containers: Containers) -> None:
    process, client = containers.start("--allow-module-plugins")
    assert listing(client) == []

    first = client.load(TALKER, name="a")
    assert (first.success, first.error_message, first.full_node_name, first.unique_id) == (True, "", "/a", 1)
    assert client.load(LISTENER).unique_id == 2
    third = client.load(TALKER, name="b", namespace="/grp")
    assert (third.full_node_name, third.unique_id) == ("/grp/b", 3)
    assert listing(client) == [(1, "/a"), (2, "/listener"), (3, "/grp/b")]

    assert client.unload(2).success
    again = client.unload(2)
    assert (again.success, again.error_message) == (False, "No node found with unique_id: 2")
    assert client.load(TALKER, name="c").unique_id == 4, "ids are never reused"

    # a request that fails validation uses no id ...
    assert_failed(client.load(TALKER, extra={"use_intra_process_comms": "yes"}))
    assert_failed(client.load(TALKER, log_level=7))
    assert client.load(TALKER, name="d").unique_id == 5
    # ... a constructor that throws uses one up (the id is allocated before the constructor runs)
    assert_failed(client.load(f"{PLUGINS}:ThrowingComponent", "tests"), prefix=CONSTRUCTOR)
    assert client.load(TALKER, name="e").unique_id == 7
    assert_failed(client.load(TALKER, parameters={"rate": -1.0}), prefix=CONSTRUCTOR)
    assert client.load(TALKER, name="f").unique_id == 9
    # plugin resolution failures come before the id too
    assert_failed(client.load("components::Nope"), UNKNOWN_PLUGIN)
    assert client.load(TALKER, name="g").unique_id == 10

    assert client.unload(1).success
    assert listing(client) == [(3, "/grp/b"), (4, "/c"), (5, "/d"), (7, "/e"), (9, "/f"), (10, "/g")]
    for uid in (3, 4, 5, 7, 9, 10):
        assert client.unload(uid).success
    assert listing(client) == []
    assert client.load(TALKER).unique_id == 11
    assert listing(client) == [(11, "/talker")]
    assert process.stop() == 0, process.output


def test_name_namespace_remaps_and_parameters_reach_the_component(containers: Containers,
                                                                  probe: Node) -> None:
    _, client = containers.start()
    received = Received(probe, "/ns/other")
    response = client.load(TALKER, name="speaker", namespace="/ns", parameters={"rate": 20.0},
                           remaps=["chatter:=other"])
    assert response.success and response.full_node_name == "/ns/speaker", response

    assert wait_until(lambda: ("speaker", "/ns") in node_names(probe), 10.0)
    assert wait_until(lambda: len(received.messages) >= 3, 10.0, probe), received.messages
    assert all(re.fullmatch(r"Hello World: \d+", m) for m in received.messages)
    topics = dict(probe.get_publisher_names_and_types_by_node("speaker", "/ns"))
    assert topics.get("/ns/other") == ["std_msgs/msg/String"]
    assert "/ns/chatter" not in topics and "/chatter" not in topics
    assert get_parameter(probe, "/ns/speaker", "rate") == 20.0
    # the request's parameters are overrides for that component only
    assert client.load(TALKER).success
    assert get_parameter(probe, "/talker", "rate") == 2.0
    # well-typed extra arguments are accepted, unknown ones ignored
    accepted = client.load(TALKER, name="extra", extra={"use_intra_process_comms": True,
                                                        "forward_global_arguments": False, "unknown": "x"})
    assert accepted.success and accepted.full_node_name == "/extra", accepted


def test_renamed_container_does_not_forward_global_arguments(containers: Containers, probe: Node) -> None:
    _, client = containers.start("--ros-args", "-r", "__node:=box", "-r", "__ns:=/rig", "-p", "rate:=20.0",
                                 "-r", "chatter:=global_chatter", container="/rig/box")
    services = dict(probe.get_service_names_and_types())
    for service, type_name in (("load_node", "LoadNode"), ("unload_node", "UnloadNode"),
                               ("list_nodes", "ListNodes")):
        assert services.get(f"/rig/box/_container/{service}") == [f"composition_interfaces/srv/{type_name}"]
    assert not any(name.startswith("/ComponentManager/") for name in services)

    # by default the container's own --ros-args (its __node/__ns rename, -p, -r) do not touch components
    plain = client.load(TALKER)
    assert (plain.success, plain.full_node_name) == (True, "/talker"), plain
    assert get_parameter(probe, "/talker", "rate") == 2.0
    assert wait_until(lambda: "/chatter" in dict(probe.get_publisher_names_and_types_by_node("talker", "/")),
                      10.0)

    # forward_global_arguments: the global arguments apply as they would to any node of the process; the
    # request's own node name (a node-local argument) still wins over the container's __node rename
    named = client.load(TALKER, name="fwd", extra={"forward_global_arguments": True})
    assert (named.success, named.full_node_name) == (True, "/rig/fwd"), named
    assert get_parameter(probe, "/rig/fwd", "rate") == 20.0
    assert wait_until(lambda: "/rig/global_chatter" in dict(
        probe.get_publisher_names_and_types_by_node("fwd", "/rig")), 10.0)
    # without a name of its own it takes the container's (rclcpp semantics: global __node applies to all)
    unnamed = client.load(TALKER, extra={"forward_global_arguments": True})
    assert (unnamed.success, unnamed.full_node_name) == (True, "/rig/box"), unnamed
    assert listing(client) == [(1, "/talker"), (2, "/rig/fwd"), (3, "/rig/box")]


def test_log_level_is_applied_to_the_component(containers: Containers, probe: Node) -> None:
    process, client = containers.start("--allow-module-plugins")
    rosout: list[Log] = []
    probe.create_subscription(Log, "/rosout", rosout.append,
                              QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                                         durability=DurabilityPolicy.TRANSIENT_LOCAL))
    for name, level in (("lvl_error", 40), ("lvl_default", 0), ("lvl_debug", 10)):
        response = client.load(f"{PLUGINS}:LoggingComponent", "tests", name=name, log_level=level)
        assert response.success, response

    def seen(name: str, text: str) -> bool:
        return any(m.name == name and m.msg == f"{text} from {name}" for m in rosout)

    assert wait_until(lambda: seen("lvl_debug", "info-probe") and seen("lvl_default", "info-probe"),
                      10.0, probe), [(m.name, m.msg) for m in rosout]
    assert seen("lvl_debug", "debug-probe")
    assert process.stop() == 0
    output = process.output
    assert "debug-probe from lvl_debug" in output and "info-probe from lvl_debug" in output
    assert "info-probe from lvl_default" in output and "debug-probe from lvl_default" not in output
    assert "probe from lvl_error" not in output
    assert not any(m.name == "lvl_error" for m in rosout)


def test_module_plugins_are_refused_by_default(containers: Containers) -> None:
    process, client = containers.start()
    refused = client.load(f"{PLUGINS}:LoggingComponent", "tests")
    assert_failed(refused, prefix=UNKNOWN_PLUGIN)
    assert "--allow-module-plugins" in refused.error_message
    # refused before anything is imported: the module that fails on import is not even tried
    broken = client.load("tests.container_test_broken_plugin:Anything", "tests")
    assert_failed(broken, prefix=UNKNOWN_PLUGIN)
    assert process.alive() and listing(client) == []
    assert client.load(TALKER).unique_id == 1


# --- every error, against one container that must survive them all ------------------------------------------
@pytest.fixture(scope="module")
def error_container(ros: None) -> Iterator[tuple[ContainerProcess, ContainerClient, Node]]:
    node = Node("container_error_probe")
    # a name of its own: it runs alongside the other tests' /ComponentManager containers
    process = ContainerProcess("--allow-module-plugins", name="error_container", cwd=str(REPO))
    with process:
        client = ContainerClient(node, "/error_container")
        client.wait()
        loaded = client.load(TALKER, name="survivor", remaps=["chatter:=survivor_chatter"])
        assert loaded.success and loaded.unique_id == 1
        yield process, client, node
        assert process.stop() == 0, process.output
    assert not pid_alive(process.pid)
    node.destroy_node()


LOAD_ERRORS = {
    "unknown package": (dict(plugin=TALKER, package="no_such_package"), UNKNOWN_PACKAGE, None),
    "unknown plugin": (dict(plugin="components::NoSuchComponent"), UNKNOWN_PLUGIN, None),
    "plugin of another package": (dict(plugin=TALKER, package="tests"), UNKNOWN_PACKAGE, None),
    "module import raises": (
        dict(plugin="tests.container_test_broken_plugin:Anything", package="tests"),
        "Failed to load library: ImportError: container_test_broken_plugin refuses to be imported", None),
    "module missing": (dict(plugin="tests.no_such_module:Anything", package="tests"),
                       None, "Failed to load library: ModuleNotFoundError: "),
    "module plugin under another package": (dict(plugin=f"{PLUGINS}:LoggingComponent", package="components"),
                                            UNKNOWN_PACKAGE, None),
    "class missing in module": (dict(plugin=f"{PLUGINS}:NoSuchClass", package="tests"), UNKNOWN_PLUGIN, None),
    "class is not a node": (dict(plugin=f"{PLUGINS}:NotANode", package="tests"), None, UNKNOWN_PLUGIN),
    "constructor raises": (dict(plugin=f"{PLUGINS}:ThrowingComponent", package="tests"),
                           CONSTRUCTOR + "deliberate failure in ThrowingComponent.__init__", None),
    "component rejects a parameter": (dict(plugin=TALKER, parameters={"rate": 0.0}),
                                      CONSTRUCTOR + "parameter 'rate' must be in [0.01, 2000] Hz, got 0.0", None),
    "parameter of the wrong type": (dict(plugin=TALKER, parameters={"rate": "fast"}), None, CONSTRUCTOR),
    "use_intra_process_comms not a bool": (
        dict(plugin=TALKER, extra={"use_intra_process_comms": "yes"}),
        "Extra component argument 'use_intra_process_comms' must be a boolean", None),
    "forward_global_arguments not a bool": (
        dict(plugin=TALKER, extra={"forward_global_arguments": 1}),
        "Extra component argument 'forward_global_arguments' must be a boolean", None),
    "invalid log_level": (dict(plugin=TALKER, log_level=7), None, "Invalid log_level 7"),
    "malformed remap rule": (dict(plugin=TALKER, remaps=["garbage"]), None, CONSTRUCTOR),
    "relative namespace": (dict(plugin=TALKER, namespace="relative"), None, CONSTRUCTOR),
}


@pytest.mark.parametrize("case", list(LOAD_ERRORS))
def test_load_errors_leave_the_container_answering(error_container: Any, case: str) -> None:
    process, client, _ = error_container
    request, message, prefix = LOAD_ERRORS[case]
    request = dict(request)
    before = listing(client)
    assert_failed(client.load(request.pop("plugin"), **request), message, prefix=prefix)
    assert process.alive()
    assert listing(client) == before


def test_failed_constructor_leaves_no_node_behind(error_container: Any) -> None:
    """rclcpp destroys a half-built component; its node, publisher and services must not linger."""
    process, client, node = error_container
    assert_failed(client.load(f"{PLUGINS}:ThrowingComponent", "tests"), prefix=CONSTRUCTOR)
    time.sleep(0.5)  # a lingering node would have been discovered by now
    assert wait_until(lambda: ("throwing_component", "/") not in node_names(node)
                      and node.count_publishers("/thrower_output") == 0, 5.0)
    assert ("survivor", "/") in node_names(node)


@pytest.mark.parametrize("unique_id", [0, 999, 2**64 - 1])
def test_unload_unknown_id(error_container: Any, unique_id: int) -> None:
    process, client, _ = error_container
    response = client.unload(unique_id)
    assert (response.success, response.error_message) == (False, f"No node found with unique_id: {unique_id}")
    assert process.alive() and (1, "/survivor") in listing(client)


def test_unload_twice(error_container: Any) -> None:
    process, client, _ = error_container
    loaded = client.load(TALKER, name="twice", remaps=["chatter:=twice_chatter"])
    assert loaded.success
    assert client.unload(loaded.unique_id).success
    response = client.unload(loaded.unique_id)
    assert (response.success, response.error_message) == (
        False, f"No node found with unique_id: {loaded.unique_id}")
    assert process.alive() and listing(client) == [(1, "/survivor")]


# --- executors ----------------------------------------------------------------------------------------------
EXECUTOR_ARGS = {
    "single": ("--executor", "single"),
    "multi": ("--executor", "multi", "--ros-args", "-p", "thread_num:=2"),
    "isolated": ("--executor", "isolated"),
    "events": ("--executor", "events"),
}


@pytest.mark.parametrize("executor", list(EXECUTOR_ARGS))
def test_executor_runs_components(containers: Containers, probe: Node, executor: str) -> None:
    process, client = containers.start(*EXECUTOR_ARGS[executor])
    if executor == "multi":
        assert get_parameter(probe, "/ComponentManager", "thread_num") == 2
    topic = f"chatter_{executor}"
    received = Received(probe, f"/{topic}")
    assert client.load(LISTENER, remaps=[f"chatter:={topic}"]).unique_id == 1
    assert client.load(TALKER, parameters={"rate": 10.0}, remaps=[f"chatter:={topic}"]).unique_id == 2
    assert listing(client) == [(1, "/listener"), (2, "/talker")]
    assert wait_until(lambda: len(received.messages) >= 3, 10.0, probe), received.messages

    assert client.unload(2).success
    assert wait_until(lambda: probe.count_publishers(f"/{topic}") == 0, 10.0)
    assert listing(client) == [(1, "/listener")]
    assert client.load(TALKER, name="talker2", parameters={"rate": 10.0},
                       remaps=[f"chatter:={topic}"]).unique_id == 3
    count = len(received.messages)
    assert wait_until(lambda: len(received.messages) >= count + 2, 10.0, probe)
    assert process.stop() == 0
    assert re.search(r"\[listener\]: I heard: \[Hello World: \d+\]", process.output), process.output


@pytest.mark.parametrize("executor", list(EXECUTOR_ARGS))
def test_services_answer_while_a_component_callback_is_blocked(containers: Containers, probe: Node,
                                                               tmp_path: pathlib.Path, executor: str) -> None:
    process, client = containers.start("--allow-module-plugins", *EXECUTOR_ARGS[executor])
    marker = tmp_path / "blocked"
    blocker = client.load(f"{PLUGINS}:BlockingComponent", "tests",
                          parameters={"block_seconds": 5.0, "marker": str(marker)})
    assert blocker.success, blocker
    assert wait_until(marker.exists, 10.0), "the blocking callback never ran"
    # from here on the component's timer callback is (nearly) always inside its 5 s sleep: it fires again
    # 0.05 s after each sleep ends

    def answered_quickly(call: Callable[[], Any]) -> Any:
        start = time.monotonic()
        result = call()
        assert time.monotonic() - start < 2.0, "service answer stalled behind a blocked component callback"
        return result

    received = Received(probe, f"/chatter_blocked_{executor}")
    talker = answered_quickly(lambda: client.load(TALKER, parameters={"rate": 20.0},
                                                  remaps=[f"chatter:=chatter_blocked_{executor}"]))
    assert talker.success and talker.unique_id == 2
    assert answered_quickly(lambda: listing(client)) == [(1, "/blocking_component"), (2, "/talker")]
    if executor not in ("single", "events"):  # with other threads available, the other component keeps running
        assert wait_until(lambda: received.messages, 3.0, probe)
    assert answered_quickly(lambda: client.unload(2)).success

    # unloading the blocked component itself drains it: the answer waits for the running callback (at most
    # the rest of its 5 s sleep, well inside the 10 s shutdown timeout), never destroys the node under it
    start = time.monotonic()
    assert client.unload(1).success
    assert time.monotonic() - start < 8.0
    assert answered_quickly(lambda: listing(client)) == []
    assert process.stop() == 0, process.output


@pytest.mark.parametrize("thread_num", [0, -1])
def test_invalid_thread_num_is_refused(containers: Containers, thread_num: int) -> None:
    process, _ = containers.start("--executor", "multi", "--ros-args", "-p", f"thread_num:={thread_num}",
                                  wait=False)
    assert process.process.wait(timeout=20) == 2
    output = process.output
    assert "Cannot start the container: thread_num must be a positive number of threads" in output, output


# --- start-up file ------------------------------------------------------------------------------------------
def test_startup_file_loads_components(containers: Containers, probe: Node, tmp_path: pathlib.Path) -> None:
    startup = tmp_path / "components.yaml"
    startup.write_text("""\
components:
  - package: components
    plugin: components::Talker
    name: yaml_talker
    namespace: /from_file
    parameters: {rate: 10.0}
    remaps: {chatter: greetings}
  - package: components
    plugin: components::NoSuchComponent
  - package: components
    plugin: components::Listener
    namespace: /from_file
    remaps: ["chatter:=greetings"]
""")
    received = Received(probe, "/from_file/greetings")
    process, client = containers.start("--load", str(startup))
    assert listing(client) == [(1, "/from_file/yaml_talker"), (2, "/from_file/listener")]
    assert get_parameter(probe, "/from_file/yaml_talker", "rate") == 10.0
    assert wait_until(lambda: len(received.messages) >= 2, 10.0, probe)
    assert client.load(TALKER).unique_id == 3
    assert process.stop() == 0
    assert f"Failed to load component components::NoSuchComponent: {UNKNOWN_PLUGIN}" in process.output
    heard = re.search(r"\[from_file\.listener\]: I heard: \[Hello World: \d+\]", process.output)
    assert heard, process.output


def test_malformed_startup_file_is_refused(containers: Containers, tmp_path: pathlib.Path) -> None:
    startup = tmp_path / "bad.yaml"
    startup.write_text("components:\n  - plugin: components::Talker\n")
    process, _ = containers.start("--load", str(startup), wait=False)
    assert process.process.wait(timeout=20) == 2
    output = process.output
    assert "needs 'package' and 'plugin'" in output, output


# --- signals ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_unloads_components_and_exits_zero(containers: Containers, probe: Node, sig: int) -> None:
    process, client = containers.start()
    assert client.load(TALKER, namespace="/sig").unique_id == 1
    assert client.load(LISTENER, namespace="/sig").unique_id == 2
    assert wait_until(lambda: {("talker", "/sig"), ("listener", "/sig")} <= node_names(probe), 10.0)
    assert process.stop(sig) == 0, process.output
    output = process.output
    assert "Unloading /sig/listener (id 2)" in output and "Unloading /sig/talker (id 1)" in output, output
    assert output.index("Unloading /sig/listener (id 2)") < output.index("Unloading /sig/talker (id 1)")
    assert not pid_alive(process.pid)
    assert wait_until(lambda: not {("talker", "/sig"), ("listener", "/sig"), ("ComponentManager", "/")}
                      & node_names(probe), 10.0), node_names(probe)


# --- resources ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("executor", list(EXECUTOR_ARGS))
def test_load_unload_cycles_leak_nothing(containers: Containers, probe: Node, executor: str) -> None:
    process, client = containers.start(*EXECUTOR_ARGS[executor])
    samples: dict[int, tuple[int, int]] = {}
    for cycle in range(1, 101):
        loaded = client.load(TALKER, parameters={"rate": 50.0})
        assert loaded.success and loaded.unique_id == cycle, loaded
        assert client.unload(cycle).success
        if cycle in (20, 100):
            status = proc_status(process.pid)
            samples[cycle] = (int(status["Threads"]), int(status["VmRSS"].split()[0]))
    assert listing(client) == []
    assert wait_until(lambda: ("talker", "/") not in node_names(probe), 5.0), node_names(probe)
    assert wait_until(lambda: not [i for i in probe.get_publishers_info_by_topic("/chatter")
                                   if i.node_name == "talker"], 5.0)
    (threads_20, rss_20), (threads_100, rss_100) = samples[20], samples[100]
    # Fast DDS may start a thread of its own now and then; a leak would add one per cycle (80 here)
    assert threads_100 - threads_20 <= 2, f"threads grew from {threads_20} to {threads_100}"
    # ~0.4 MB measured; rclpy's type description service alone would add ~8.5 MB (see the next test)
    assert rss_100 - rss_20 < 4 * 1024, f"VmRSS grew by {(rss_100 - rss_20) / 1024:.1f} MB in 80 cycles"


def test_type_description_service_is_off_unless_requested(containers: Containers, probe: Node) -> None:
    """Off by default (rclpy leaks ~105 kB per node that had it); a load request can switch it on."""
    process, client = containers.start()
    assert client.load(TALKER, name="plain").success
    assert client.load(TALKER, name="described", parameters={"start_type_description_service": True}).success
    services = lambda: {name for name, _ in probe.get_service_names_and_types()}  # noqa: E731
    assert wait_until(lambda: "/described/get_type_description" in services(), 10.0, probe)
    assert "/plain/get_type_description" not in services()
    assert process.stop() == 0
    assert process.stop() == 0
