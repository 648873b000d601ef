"""``ipc-component``, the ``ros2 component``-like command line, run as users run it: the installed console
script as a subprocess, against real container processes.

Two containers live for the whole module: ``/ComponentManager`` (started with ``--allow-module-plugins``
in a temporary directory holding ``cli_probe.py``, a component that writes down what it received) and
``/other`` (renamed with ``--ros-args -r __node:=other``). After every test a plain rclpy client unloads
whatever is left, so each test starts with empty containers (unique ids keep growing, so tests read them
from the replies instead of assuming them).
"""
from __future__ import annotations

import json
import os
import pathlib
import re
import shutil
import subprocess
import sys
import tomllib
from typing import Any, Iterator

import pytest
import rclpy

from container_process import ContainerClient, ContainerProcess, wait_until
from ipc_testing.held_participant import HELD, held_participant_library
from ipc_testing.process import run_commands
from ipc_testing.process_context import process_context

IPC_COMPONENT = shutil.which("ipc-component", path=str(pathlib.Path(sys.executable).parent)) \
    or shutil.which("ipc-component")
MAIN, OTHER = "/ComponentManager", "/other"
TALKER, LISTENER = "components::Talker", "components::Listener"
PROBE = "cli_probe:Probe"
# Bare `list` watches the graph 0.6 s by default (ros2cli: 0.5 s); on a machine busy with the whole test suite
# a container can take longer to show up, and these tests check what is listed, not how fast.
LIST_ALL = ("list", "--spin-time", "3")
# rcl refuses to initialize with this: a command that contacts ROS at all fails with rcl's error.
NO_ROS = {"ROS_DOMAIN_ID": "not_a_domain"}
PYPROJECT = pathlib.Path(__file__).resolve().parents[1] / "pyproject.toml"

PROBE_SOURCE = '''
"""A component that writes down, once it runs, what the container gave it."""
import json
import os

from component_container.component_node import ComponentNode


class Probe(ComponentNode):
    def __init__(self, **kwargs):
        super().__init__("probe", automatically_declare_parameters_from_overrides=True, **kwargs)
        self._reported = False
        self._timer = self.create_timer(0.05, self._report)

    def _report(self):
        if self._reported:
            return
        self._reported = True
        parameters = {}
        for name in self._parameters:
            parameter = self.get_parameter(name)
            value = parameter.value
            if not isinstance(value, (bool, int, float, str, type(None))):
                value = list(value)
            parameters[name] = [parameter.type_.name, value]
        report = {
            "full_name": self.get_fully_qualified_name(),
            "chatter": self.resolve_topic_name("chatter"),
            "log_level": int(self.get_logger().get_effective_level()),
            "intra_process": self.uses_intra_process,
            "parameters": parameters,
        }
        path = self.get_parameter("report").value
        with open(path + ".tmp", "w") as stream:
            json.dump(report, stream)
        os.replace(path + ".tmp", path)
'''


# --- helpers ----------------------------------------------------------------------------------------------
def cli(*args: str, timeout: float = 90.0, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """Run ``ipc-component`` with ``args`` (``env``: variables changed for it); a generous ``timeout`` only
    catches a CLI that hangs, reported with its output and stacks (ipc_testing.process.run_command)."""
    return cli_parallel(args, timeout=timeout, env=env)[0]


def cli_parallel(*commands: tuple[str, ...], timeout: float = 90.0,
                 env: dict[str, str] | None = None) -> list[subprocess.CompletedProcess]:
    """Run several ``ipc-component`` commands at the same time (each waits for discovery on its own)."""
    assert IPC_COMPONENT, "the ipc-component console script is not installed next to this Python"
    return run_commands([[IPC_COMPONENT, *args] for args in commands], timeout, dict(os.environ, **(env or {})))


def lines(*texts: str) -> str:
    return "".join(f"{text}\n" for text in texts)


ANSI_COLOR = re.compile(r"\x1b\[[0-9;]*m")
FASTDDS_DIAGNOSTIC = re.compile(r"\d{4}-\d\d-\d\d [\d:.]+ \[[A-Z_]+ (Error|Warning)\] ")


# faulthandler's report of a command whose participant Fast DDS held at its end (ipc_component.ros_session.end_ros).
HELD_TEARDOWN = re.compile(r"Timeout \(\d+:\d\d:\d\d\)!\n(?:(?:Current thread|Thread) 0x[0-9a-f]+ \(most recent call "
                           r"first\):\n(?:  File .*\n)*\n?)+")


def ours(stderr: str) -> str:
    """``stderr`` without Fast DDS's own diagnostics (e.g. a shared-memory port that another process holds,
    common when many participants start at once): they are not the command's output, and must not be in stdout.
    Nor the stacks of a teardown that Fast DDS's livelock held (about one command in a few hundred in a suite run):
    the command still ends with its own output and status, which is what these tests check; the teardown's own
    tests force the livelock and read the report."""
    return "".join(line for line in HELD_TEARDOWN.sub("", stderr).splitlines(keepends=True)
                   if not FASTDDS_DIAGNOSTIC.match(ANSI_COLOR.sub("", line)))


def assert_ok(result: subprocess.CompletedProcess, stdout: str) -> None:
    assert (result.returncode, ours(result.stderr), result.stdout) == (0, "", stdout), result


def assert_fails(result: subprocess.CompletedProcess, stderr: str, stdout: str = "") -> None:
    assert (result.returncode, ours(result.stderr), result.stdout) == (1, stderr, stdout), result


def searched(domain: str | None = None) -> str:
    """The line that says where a search that found nothing looked (the suite's discovery range is LOCALHOST)."""
    return (f"    Searched ROS_DOMAIN_ID={domain or os.environ['ROS_DOMAIN_ID']}, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST: "
            "a container started with other values is not seen, check them in both shells.")


def read_report(path: pathlib.Path, timeout: float = 20.0) -> dict[str, Any]:
    assert wait_until(path.exists, timeout), f"the probe component never wrote {path}"
    return json.loads(path.read_text())


# --- fixtures ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def probe_dir(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    directory = tmp_path_factory.mktemp("cli_probe")
    (directory / "cli_probe.py").write_text(PROBE_SOURCE)
    return directory


@pytest.fixture(scope="module")
def ros_node() -> Iterator[Any]:
    node = rclpy.create_node("_test_cli_helper", context=process_context())
    try:
        yield node
    finally:
        node.destroy_node()


@pytest.fixture(scope="module")
def containers(probe_dir: pathlib.Path, ros_node: Any) -> Iterator[dict[str, ContainerClient]]:
    """``/ComponentManager`` and ``/other``, running until the module ends, with a client for each."""
    with ContainerProcess("--allow-module-plugins", cwd=str(probe_dir)) as main, \
            ContainerProcess(name="other") as other:
        try:
            clients = {MAIN: ContainerClient(ros_node, MAIN), OTHER: ContainerClient(ros_node, OTHER)}
            for client in clients.values():
                client.wait(timeout=30.0)
            yield clients
        finally:
            for process in (main, other):
                assert process.stop() == 0, process.output
    assert not main.alive() and not other.alive()


@pytest.fixture
def clients(containers: dict[str, ContainerClient]) -> Iterator[dict[str, ContainerClient]]:
    """The module's containers, emptied again after the test."""
    yield containers
    for client in containers.values():
        listing = client.list()
        for unique_id in listing.unique_ids:
            assert client.unload(unique_id).success


def load(client: ContainerClient, plugin: str, **kwargs: Any) -> tuple[int, str]:
    response = client.load(plugin, **kwargs)
    assert response.success, response.error_message
    return response.unique_id, response.full_node_name


# --- list -------------------------------------------------------------------------------------------------
def test_list_shows_every_container_and_its_components(clients: dict[str, ContainerClient]) -> None:
    talker = load(clients[MAIN], TALKER)
    listener = load(clients[MAIN], LISTENER, namespace="/ns")
    other_talker = load(clients[OTHER], TALKER, name="other_talker")
    result = cli(*LIST_ALL)
    assert_ok(result, lines(
        MAIN, f"  {talker[0]}  /talker", f"  {listener[0]}  /ns/listener",
        OTHER, f"  {other_talker[0]}  /other_talker"))


def test_list_containers_only_and_empty_containers(clients: dict[str, ContainerClient]) -> None:
    talker = load(clients[MAIN], TALKER)
    everything, containers_only = cli_parallel(LIST_ALL, (*LIST_ALL, "--containers-only"))
    assert_ok(everything, lines(MAIN, f"  {talker[0]}  /talker", OTHER))
    assert_ok(containers_only, lines(MAIN, OTHER))


def test_list_one_container(clients: dict[str, ContainerClient]) -> None:
    load(clients[MAIN], TALKER)
    first = load(clients[OTHER], TALKER)
    second = load(clients[OTHER], LISTENER, name="heard")
    by_other, only_other, empty_main = cli_parallel(
        ("list", OTHER), ("list", OTHER, "--containers-only"), ("list", MAIN, "--containers-only"))
    assert_ok(by_other, lines(f"{first[0]}  /talker", f"{second[0]}  /heard"))
    assert_ok(only_other, "")
    assert_ok(empty_main, "")


def test_list_container_without_components_prints_nothing(clients: dict[str, ContainerClient]) -> None:
    assert_ok(cli("list", OTHER), "")


def test_list_that_finds_no_container_says_where_it_looked() -> None:
    # Domain 230 is outside the suite's range of domains (conftest): no container can be there.
    result = cli("list", "--spin-time", "0.3", env={"ROS_DOMAIN_ID": "230"})
    assert (result.returncode, result.stdout, ours(result.stderr)) == (
        0, "", lines("No container found", searched("230"))), result  # stdout stays as ros2 component's: empty


def test_fast_dds_diagnostics_go_to_stderr_not_into_the_output(clients: dict[str, ContainerClient]) -> None:
    # A statistics topic Fast DDS does not know: it logs an error and goes on without it.
    result = cli("list", OTHER, env={"FASTDDS_STATISTICS": "NO_SUCH_TOPIC"})
    assert_ok(result, "")
    assert "Topic NO_SUCH_TOPIC is not a valid statistics topic name/alias" in result.stderr, result


def test_the_fast_dds_profile_goes_through_the_variable_fast_dds_reads() -> None:
    # Fast DDS 3 (Kilted) reads FASTRTPS_DEFAULT_PROFILES_FILE too, but warns on stdout that it is deprecated.
    result = cli("list", "--spin-time", "0.3", env={"ROS_DOMAIN_ID": "230"})
    assert "deprecated" not in (result.stdout + result.stderr).lower(), result


@pytest.mark.parametrize("env, message", [
    ({"ROS_DOMAIN_ID": "233"}, "ROS_DOMAIN_ID 233 is out of range: Fast DDS accepts 0 to 232"),
    ({"ROS_STATIC_PEERS": "no-such-host.invalid"},
     "Could not start ROS: error creating node: Unable to resolve peer no-such-host.invalid"),
])
def test_a_ros_setting_that_cannot_work_is_named(env: dict[str, str], message: str) -> None:
    assert_fails(cli("list", env=env), lines(message))  # Fast DDS alone ends with status 1 and says nothing


# --- unknown containers -------------------------------------------------------------------------------------
def test_unknown_container_for_every_verb(clients: dict[str, ContainerClient]) -> None:
    results = cli_parallel(
        ("list", "/nowhere"), ("list", "/nowhere", "--containers-only"),
        ("load", "/nowhere", "components", TALKER), ("unload", "/nowhere", "1"),
        # the full name is required, as with ros2 component
        ("list", "ComponentManager"))
    for result, name in zip(results, ["/nowhere"] * 4 + ["ComponentManager"]):
        assert_fails(result, lines(f"Unable to find container node '{name}'", searched()))  # gave up: no hang
    assert len(clients[MAIN].list().unique_ids) == 0


def test_a_node_without_the_container_services_is_no_container(
        clients: dict[str, ContainerClient]) -> None:
    talker = load(clients[MAIN], TALKER, name="not_a_container")
    listed, loaded = cli_parallel(LIST_ALL, ("load", "/not_a_container", "components", TALKER))
    assert_ok(listed, lines(MAIN, f"  {talker[0]}  /not_a_container", OTHER))
    assert_fails(loaded, lines("Unable to find container node '/not_a_container'", searched()))


def test_a_record_verb_that_finds_no_recorder_names_what_it_found(clients: dict[str, ContainerClient],
                                                                  tmp_path: pathlib.Path) -> None:
    load(clients[MAIN], "components::Recorder", name="record_cli_a", namespace=MAIN,
         parameters={"storage.uri": str(tmp_path / "bag"), "record.topics": ["/chatter"]})
    load(clients[OTHER], TALKER)
    status, stop = cli_parallel(("record", "status", "--session", "cli_b", "--spin-time", "3"),
                                ("record", "stop", "--session", "cli_b", "--spin-time", "3"))
    found = lines(f"    {MAIN}: {MAIN}/record_cli_a (session 'cli_a')", f"    {OTHER}: no recorder among 1 component(s)")
    assert_fails(status, "No recorder of session 'cli_b' found in the 2 container(s) discovered\n" + found)
    assert_fails(stop, "No recorder of session 'cli_b' found in the 2 container(s) discovered\n" + found)
    nowhere = cli("record", "status", "--spin-time", "0.3", env={"ROS_DOMAIN_ID": "230"})
    assert_fails(nowhere, lines("No recorder found: no container discovered within 0.3 s (--spin-time)", searched("230")))


# --- load -------------------------------------------------------------------------------------------------
def test_load(clients: dict[str, ContainerClient]) -> None:
    result = cli("load", MAIN, "components", TALKER)
    (unique_id,) = clients[MAIN].list().unique_ids
    assert_ok(result, lines(f"Loaded component {unique_id} into '{MAIN}' container node as '/talker'"))
    assert list(clients[MAIN].list().full_node_names) == ["/talker"]


def test_load_quiet_then_list(clients: dict[str, ContainerClient]) -> None:
    result = cli("load", OTHER, "components", LISTENER, "-q")
    (unique_id,) = clients[OTHER].list().unique_ids
    assert_ok(result, lines(f"{unique_id}  /listener"))
    assert_ok(cli("list", OTHER), lines(f"{unique_id}  /listener"))


def test_load_options_reach_the_component(clients: dict[str, ContainerClient], tmp_path: pathlib.Path) -> None:
    report = tmp_path / "report.json"
    result = cli("load", MAIN, "cli_probe", PROBE, "-n", "probe_a", "--node-namespace", "/cli",
                 "-r", "chatter:=/remapped/chatter", "--log-level", "debug",
                 "-p", f"report:={report}", "-p", "rate:=2.5", "-p", "count:=3", "-p", "flag:=true",
                 "-p", "label:=hello world", "-p", "ints:=[1, 2, 3]", "-p", "quoted:='42'",
                 "-p", "url:=http://host:80/a:=b",
                 "-e", "use_intra_process_comms:=true")
    (unique_id,) = clients[MAIN].list().unique_ids
    assert_ok(result, lines(
        f"Loaded component {unique_id} into '{MAIN}' container node as '/cli/probe_a'"))
    received = read_report(report)
    assert received["full_name"] == "/cli/probe_a"
    assert received["chatter"] == "/remapped/chatter"
    assert received["log_level"] == 10
    assert received["intra_process"] is True
    parameters = received["parameters"]
    assert parameters["rate"] == ["DOUBLE", 2.5]
    assert parameters["count"] == ["INTEGER", 3]
    assert parameters["flag"] == ["BOOL", True]
    assert parameters["label"] == ["STRING", "hello world"]
    assert parameters["ints"] == ["INTEGER_ARRAY", [1, 2, 3]]
    assert parameters["quoted"] == ["STRING", "42"]
    assert parameters["url"] == ["STRING", "http://host:80/a:=b"]  # split on the first := only
    assert_ok(cli("list", MAIN), lines(f"{unique_id}  /cli/probe_a"))


@pytest.mark.parametrize(("level", "expected"), [("40", 40), ("Fatal", 50), (None, 20)])
def test_load_log_level_names_and_numbers(clients: dict[str, ContainerClient], tmp_path: pathlib.Path,
                                          level: str | None, expected: int) -> None:
    # Each case names its node differently: a logger's level outlives the component in the container.
    name = f"probe_{expected}"
    report = tmp_path / "report.json"
    args = ["load", MAIN, "cli_probe", PROBE, "-q", "-n", name, "-p", f"report:={report}"]
    if level is not None:
        args += ["--log-level", level]
    result = cli(*args)
    (unique_id,) = clients[MAIN].list().unique_ids
    assert_ok(result, lines(f"{unique_id}  /{name}"))
    received = read_report(report)
    assert received["log_level"] == expected
    assert received["intra_process"] is False


def test_load_unknown_package_and_plugin(clients: dict[str, ContainerClient]) -> None:
    package, plugin = cli_parallel(("load", MAIN, "no_such_package", TALKER),
                                   ("load", MAIN, "components", "components::NoSuchThing"))
    assert package.returncode == 1 and package.stdout == "", package
    assert ours(package.stderr).startswith(
        "Failed to load component: Could not find requested resource in ament index: package 'no_such_package' is "
        "not installed in the Python environment "), package.stderr
    assert "(no entry point of the group 'rclpy_components' belongs to it); 'ipc-component types' run in that " \
           "environment lists the packages it has\n" in package.stderr, package.stderr
    assert_fails(plugin, lines("Failed to load component: Failed to find class with the requested plugin name."))
    assert len(clients[MAIN].list().unique_ids) == 0


def test_load_extra_argument_must_be_a_boolean(clients: dict[str, ContainerClient]) -> None:
    result = cli("load", MAIN, "components", TALKER, "-e", "use_intra_process_comms:=notabool")
    assert_fails(result, lines(
        "Failed to load component: Extra component argument 'use_intra_process_comms' must be a boolean"))
    assert len(clients[MAIN].list().unique_ids) == 0


def test_load_warns_about_parameters_the_component_does_not_declare(clients: dict[str, ContainerClient]) -> None:
    result = cli("load", MAIN, "components", "components::ImuDriver", "-p", "no_such_param:=1", "-p", "rat:=50.0")
    (unique_id,) = clients[MAIN].list().unique_ids
    assert (result.returncode, result.stdout, ours(result.stderr)) == (0, lines(
        f"Loaded component {unique_id} into '{MAIN}' container node as '/imu'"), lines(
        "Warning: /imu does not declare the parameters 'no_such_param', 'rat' (did you mean 'rate'?): ignored")), \
        result
    declared = cli("load", MAIN, "components", TALKER, "-p", "rate:=5.0")  # nothing to say
    assert declared.returncode == 0 and ours(declared.stderr) == "", declared


def test_load_constructor_failure(clients: dict[str, ContainerClient]) -> None:
    result = cli("load", OTHER, "components", TALKER, "-p", "rate:=-1.0")
    assert_fails(result, lines("Failed to load component: Component constructor threw an exception: "
                               "parameter 'rate' must be in [0.01, 2000] Hz, got -1.0"))


@pytest.mark.parametrize(("args", "message"), [
    (["-p", "foo"], "Malformed parameter 'foo': expected name:=value"),
    (["-p", ":=3"], "Malformed parameter ':=3': expected name:=value"),
    (["-e", "use_intra_process_comms"],
     "Malformed extra argument 'use_intra_process_comms': expected name:=value"),
    (["-r", "chatter"], "Malformed remap rule 'chatter': expected from:=to"),
    (["-p", "big:=9223372036854775808"],
     "Invalid parameter 'big:=9223372036854775808': integer out of the 64-bit signed range"),
    (["-e", "big:=[1, -9223372036854775809]"],
     "Invalid extra argument 'big:=[1, -9223372036854775809]': integer out of the 64-bit signed range"),
    (["--log-level", "loud"], "Invalid log level 'loud': use DEBUG, INFO, WARN, ERROR or FATAL (any case), "
                              "or 10, 20, 30, 40 or 50"),
    (["--log-level", "15"], "Invalid log level '15': use DEBUG, INFO, WARN, ERROR or FATAL (any case), "
                            "or 10, 20, 30, 40 or 50"),
])
def test_load_malformed_arguments_fail_before_contacting_anyone(args: list[str], message: str) -> None:
    # No container fixture, and no ROS at all: these must fail before any ROS contact (no waiting for discovery).
    result = cli("load", "/nowhere", "components", TALKER, *args, env=NO_ROS)
    assert_fails(result, lines(message))


# --- unload -----------------------------------------------------------------------------------------------
def test_unload(clients: dict[str, ContainerClient]) -> None:
    unique_id, _ = load(clients[MAIN], TALKER)
    kept, _ = load(clients[MAIN], LISTENER)
    assert_ok(cli("unload", MAIN, str(unique_id)),
              lines(f"Unloaded component {unique_id} from '{MAIN}' container node"))
    assert list(clients[MAIN].list().unique_ids) == [kept]


def test_unload_several_and_quiet(clients: dict[str, ContainerClient]) -> None:
    ids = [load(clients[OTHER], TALKER, name=f"t{i}")[0] for i in range(3)]
    verbose, quiet = cli_parallel(("unload", OTHER, str(ids[0]), str(ids[1])),
                                  ("unload", OTHER, str(ids[2]), "-q"))
    assert_ok(verbose, lines(*(f"Unloaded component {uid} from '{OTHER}' container node" for uid in ids[:2])))
    assert_ok(quiet, lines(str(ids[2])))
    assert list(clients[OTHER].list().unique_ids) == []


def test_unload_unknown_id(clients: dict[str, ContainerClient]) -> None:
    assert_fails(cli("unload", MAIN, "4242"), lines(
        f"Failed to unload component 4242 from '{MAIN}' container node",
        "    No node found with unique_id: 4242"))


def test_unload_tries_every_id_and_reports_each_failure(clients: dict[str, ContainerClient]) -> None:
    first, _ = load(clients[MAIN], TALKER)
    second, _ = load(clients[MAIN], LISTENER)
    result = cli("unload", MAIN, str(first), "4242", str(second), "4343")
    assert_fails(result,
                 lines(f"Failed to unload component 4242 from '{MAIN}' container node",
                       "    No node found with unique_id: 4242",
                       f"Failed to unload component 4343 from '{MAIN}' container node",
                       "    No node found with unique_id: 4343"),
                 stdout=lines(f"Unloaded component {first} from '{MAIN}' container node",
                              f"Unloaded component {second} from '{MAIN}' container node"))
    assert list(clients[MAIN].list().unique_ids) == []


def test_unload_invalid_id() -> None:
    result = cli("unload", "/nowhere", "abc", env=NO_ROS)  # refused before any ROS contact
    assert_fails(result, lines("Invalid component unique id 'abc': expected a non-negative integer"))


def test_a_participant_that_never_finishes_its_destruction_does_not_hold_the_command(
        clients: dict[str, ContainerClient], tmp_path_factory: pytest.TempPathFactory) -> None:
    """Fast DDS's livelock at a command's end (ipc_testing.held_participant: destroying the participant never
    returns, and holds the GIL): each command still ends, with its own output and status, after the Python
    stacks of its held teardown (ipc_component.ros_session.TEARDOWN_LIMIT later)."""
    held = {"LD_PRELOAD": str(held_participant_library(tmp_path_factory.getbasetemp()))}
    loaded, refused = cli_parallel(("load", OTHER, "components", TALKER), ("unload", MAIN, "4242"), env=held)
    (unique_id,) = clients[OTHER].list().unique_ids
    assert (loaded.returncode, loaded.stdout) == (
        0, lines(f"Loaded component {unique_id} into '{OTHER}' container node as '/talker'")), loaded
    assert (refused.returncode, refused.stdout) == (1, ""), refused
    assert f"Failed to unload component 4242 from '{MAIN}' container node" in refused.stderr, refused
    for result in (loaded, refused):
        assert HELD in result.stderr and "Timeout" in result.stderr and "in destroy_node" in result.stderr, result


# --- types ------------------------------------------------------------------------------------------------
def registered_plugins() -> dict[str, list[str]]:
    """What this project registers, read from pyproject.toml: plugin names per Python package of their class."""
    with open(PYPROJECT, "rb") as stream:
        registered = tomllib.load(stream)["project"]["entry-points"]["rclpy_components"]
    packages: dict[str, list[str]] = {}
    for name, target in registered.items():
        packages.setdefault(target.split(":")[0].split(".")[0], []).append(name)
    return {package: sorted(names) for package, names in sorted(packages.items())}


def test_types() -> None:
    plugins = registered_plugins()
    assert {TALKER, LISTENER, "components::Recorder"} <= set(plugins["components"])
    expected = "".join(lines(package, *(f"  {name}" for name in names)) for package, names in plugins.items())
    assert_ok(cli("types"), expected)


def test_types_of_one_package() -> None:
    assert_ok(cli("types", "components"), lines(*registered_plugins()["components"]))


def test_types_unknown_package() -> None:
    result = cli("types", "no_such_package")
    assert_fails(result, lines(f"Unable to find package 'no_such_package': it is not installed in the Python "
                               f"environment {sys.prefix} (no entry point of the group 'rclpy_components' "
                               "belongs to it)"))


# --- command line -----------------------------------------------------------------------------------------
def test_usage_errors_are_argparse_errors() -> None:
    for args in ([], ["frobnicate"], ["load", MAIN], ["unload", MAIN]):
        result = cli(*args)
        assert result.returncode == 2, result
        assert result.stdout == ""
        assert result.stderr.startswith("usage: ipc-component"), result


def test_bag_info_prints_what_ros2_bag_info_prints(tmp_path: pathlib.Path) -> None:
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    from baglib.write.writer import BagWriter
    from baglib.format.metadata import TopicInfo

    writer = BagWriter(tmp_path / "info_bag")
    writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String"))
    writer.add_topic(TopicInfo("/silent", "std_msgs/msg/String"))
    for i in range(3):
        writer.write("/chatter", serialize_message(String(data=str(i))), 1_700_000_000_000_000_000 + i * 500_000_000,
                     1_700_000_000_000_000_000 + i * 500_000_000)
    writer.close()
    result = cli("bag", "info", str(tmp_path / "info_bag"))
    assert result.returncode == 0, result.stderr
    out = result.stdout.splitlines()
    assert out[0] == "Files:             info_bag_0.mcap"
    assert out[2] == "Storage id:        mcap"
    assert out[4] == "Duration:          1.000000000s"
    assert out[5].endswith("(1700000000.000000000)") and out[6].endswith("(1700000001.000000000)")
    assert out[7] == "Messages:          3"
    assert out[8] == ("Topic information: Topic: /chatter | Type: std_msgs/msg/String | Count: 3 | "
                      "Serialization Format: cdr")
    assert out[9] == ("                   Topic: /silent | Type: std_msgs/msg/String | Count: 0 | "
                      "Serialization Format: cdr")
    missing = cli("bag", "info", str(tmp_path / "nothing"))
    assert missing.returncode == 1
    assert f"'{tmp_path / 'nothing'}' does not exist" in missing.stderr


def info_bag(path: pathlib.Path, topics: int = 1) -> pathlib.Path:
    """A small finished bag with ``topics`` topics and three messages on the first one."""
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    from baglib.format.metadata import TopicInfo
    from baglib.write.writer import BagWriter

    with BagWriter(path) as writer:
        for n in range(topics):
            writer.add_topic(TopicInfo(f"/topic_{n}", "std_msgs/msg/String"))
        for i in range(3):
            writer.write("/topic_0", serialize_message(String(data=str(i))), 1_700_000_000_000_000_000 + i, 1_700_000_000_000_000_000 + i)
    return path


@pytest.mark.parametrize("verb", [["bag", "info", "{bag}"], ["types"]])
def test_a_closed_pipe_ends_the_command_quietly(tmp_path: pathlib.Path, verb: list[str]) -> None:
    # `... | head`: head exits after its lines and the command's next write finds the pipe closed.
    bag = info_bag(tmp_path / "bag", topics=200)
    reader, writer = os.pipe()
    os.close(reader)
    try:
        result = subprocess.run([IPC_COMPONENT, *(word.format(bag=bag) for word in verb)], stdout=writer,
                                stderr=subprocess.PIPE, text=True, timeout=60)
    finally:
        os.close(writer)
    assert (result.returncode, ours(result.stderr)) == (141, ""), result  # 128 + SIGPIPE, as the shell reports cat's


def verb_paths(parser: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    """Every verb of the parser (``("bag", "info")``...) with its own parser, sub-verbs after their parent."""
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield (*path, name), sub
                yield from verb_paths(sub, (*path, name))


def test_every_verb_has_plain_help_of_its_own(capsys: pytest.CaptureFixture[str]) -> None:
    from ipc_component.cli import build_parser, main

    paths = [path for path, _ in verb_paths(build_parser())]
    assert {("load",), ("record", "start"), ("bag", "reindex"), ("bag", "merge")} <= set(paths)
    for path in paths:
        with pytest.raises(SystemExit) as exit_:
            main([*path, "-h"])
        text = capsys.readouterr().out
        assert exit_.value.code == 0, path
        assert text.startswith(f"usage: ipc-component {' '.join(path)} "), text  # not another verb's usage
        assert "`" not in text and not re.search(r"\w\.py\b", text), text        # no markup, no source paths
        assert not re.search(r"\{,|,\}|,,", text), text                           # no empty choice


def test_the_docs_synopsis_lists_every_verb() -> None:
    from ipc_component.cli import build_parser

    text = (pathlib.Path(__file__).resolve().parents[1] / "docs" / "cli.md").read_text()
    synopsis = text.split("```sh\n", 1)[1].split("```", 1)[0]
    parser = build_parser()
    leaves = [path for path, sub in verb_paths(parser) if not any(p[:len(path)] == path and p != path
                                                                  for p, _ in verb_paths(parser))]
    missing = [" ".join(path) for path in leaves
               if not re.search(rf"^ipc-component {re.escape(' '.join(path))}( |$)", synopsis, re.MULTILINE)]
    assert missing == []
