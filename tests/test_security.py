"""Limits on the load path (issue #11): what an anonymous caller on the ROS domain can make a container do.

Real container processes over Fast DDS. ``--bag-root`` confines every path a request names (a recorder's
``storage.uri``, including its ``<uri>_N`` and default names, and its QoS override file) to one directory, after
``..`` and symlinks; errors about files name the parameter and the problem and never carry the file's
contents; ``--allow-plugins`` narrows which plugins load, and module plugins still need ``--allow-module-plugins``.
"""
from __future__ import annotations

import json
import pathlib
import subprocess
import sys
from typing import Any

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rosbags.rosbag2 import Reader
from std_srvs.srv import Trigger

from component_container.plugin_registry import UNKNOWN_PLUGIN
from container_process import REPO, ContainerClient, Containers, listing, wait_until

RECORDER = "components::Recorder"
TALKER = "components::Talker"
MODULE_PLUGIN = "tests.container_test_plugins:LoggingComponent"
IPC = {"use_intra_process_comms": True}
QOS_PARAMETER = "parameter 'record.qos_profile_overrides_path'"
URI_PARAMETER = "parameter 'storage.uri'"
SECRET = "SECRET-TOKEN"
NOT_ALLOWED = "is not allowed by this container"


@pytest.fixture()
def root(tmp_path: pathlib.Path) -> pathlib.Path:
    """The bag root, next to a directory ``outside`` that nothing may touch, and a link to it from inside."""
    (tmp_path / "root").mkdir()
    (tmp_path / "outside").mkdir()
    (tmp_path / "root" / "link").symlink_to(tmp_path / "outside")
    return tmp_path / "root"


def entries(directory: pathlib.Path) -> list[str]:
    return sorted(path.name for path in directory.iterdir())


def trigger(probe: Node, service: str) -> Trigger.Response:
    """Call a std_srvs/Trigger service once the service answers (get_stats first: it changes nothing)."""
    stats = probe.create_client(Trigger, service.rsplit("/", 1)[0] + "/get_stats")
    client = probe.create_client(Trigger, service)
    try:
        assert client.wait_for_service(timeout_sec=10.0) and stats.wait_for_service(timeout_sec=10.0)
        wait_until(lambda: _call(probe, stats, 1.0), 10.0)  # a brand-new client's first reply may be dropped
        response = _call(probe, client, 10.0)
        assert response is not None, f"no reply from {service}"
        return response
    finally:
        probe.destroy_client(client)
        probe.destroy_client(stats)


def _call(probe: Node, client: Any, timeout: float) -> Trigger.Response | None:
    future = client.call_async(Trigger.Request())
    executor = SingleThreadedExecutor(context=probe.context)
    executor.add_node(probe)
    executor.spin_until_future_complete(future, timeout_sec=timeout)
    executor.remove_node(probe)
    return future.result() if future.done() else None


def refused_load(client: ContainerClient, parameters: dict[str, Any]) -> str:
    """Load a recorder that must be refused; its error message."""
    response = client.load(RECORDER, extra=IPC, parameters={"record.topics": ["/sec_chatter"], **parameters})
    assert not response.success, response
    return response.error_message


def read_topic(uri: pathlib.Path, topic: str) -> int:
    """Messages of ``topic`` in the finished bag at ``uri``, read with rosbags."""
    with Reader(uri) as reader:
        return sum(1 for connection, _, _ in reader.messages() if connection.topic == topic)


# --- the bag root -------------------------------------------------------------------------------------------
def test_bag_root_must_be_an_existing_directory(tmp_path: pathlib.Path) -> None:
    result = subprocess.run([sys.executable, "-m", "component_container", "--bag-root", str(tmp_path / "nope")],
                            capture_output=True, text=True, timeout=60, cwd=str(REPO))
    assert result.returncode == 2
    assert "is not an existing directory" in result.stderr, result.stderr


@pytest.mark.parametrize("uri", ["{outside}/bag", "../escape", "link/bag", "{root}/link/bag"],
                         ids=["absolute", "dotdot", "symlink", "absolute_symlink"])
def test_storage_uri_outside_the_root_is_refused(containers: Containers, root: pathlib.Path, uri: str) -> None:
    process, client = containers.start("--bag-root", str(root))
    uri = uri.format(outside=root.parent / "outside", root=root)
    error = refused_load(client, {"storage.uri": uri})
    assert URI_PARAMETER in error and "outside the bag root" in error, error
    assert entries(root.parent) == ["outside", "root"] and entries(root.parent / "outside") == []
    assert entries(root) == ["link"]
    assert listing(client) == [] and process.alive()
    assert client.load(TALKER).success  # the container still serves
    assert process.stop() == 0


def test_relative_uris_and_the_default_name_land_inside_the_root(containers: Containers, probe: Node,
                                                                root: pathlib.Path) -> None:
    (root / "qos.yaml").write_text("/sec_chatter: {reliability: reliable, depth: 50}\n")
    before = set(REPO.glob("rosbag2_*"))
    process, client = containers.start("--bag-root", str(root))
    assert client.load(TALKER, extra=IPC, parameters={"rate": 20.0}, remaps=["chatter:=sec_chatter"]).success
    recorder = client.load(RECORDER, name="rel_recorder", extra=IPC, parameters={
        "storage.uri": "rel/bag", "record.topics": ["/sec_chatter"],
        "record.qos_profile_overrides_path": "qos.yaml"})
    assert recorder.success, recorder
    default = client.load(RECORDER, name="default_recorder", extra=IPC,
                          parameters={"record.topics": ["/sec_chatter"]})
    assert default.success, default

    def written() -> int:
        stats = json.loads(trigger(probe, "/rel_recorder/get_stats").message)
        return stats["current"]["topics"].get("/sec_chatter", {}).get("written", 0)

    assert wait_until(lambda: written() >= 5, 20.0), "nothing recorded"
    assert trigger(probe, "/rel_recorder/stop_recording").success
    started = trigger(probe, "/rel_recorder/start_recording")
    assert started.success and str(root / "rel" / "bag_1") in started.message, started
    assert trigger(probe, "/rel_recorder/stop_recording").success
    (root / "rel" / "bag_2").symlink_to(root.parent / "outside" / "bag_2")  # planted between two bags
    refused = trigger(probe, "/rel_recorder/start_recording")
    assert not refused.success and URI_PARAMETER in refused.message and "outside the bag root" in refused.message
    assert client.unload(recorder.unique_id).success and client.unload(default.unique_id).success
    assert read_topic(root / "rel" / "bag", "/sec_chatter") >= 5
    read_topic(root / "rel" / "bag_1", "/sec_chatter")  # finalized and readable
    default_bags = [path for path in root.iterdir() if path.name.startswith("rosbag2_")]
    assert len(default_bags) == 1, entries(root)
    read_topic(default_bags[0], "/sec_chatter")
    assert entries(root.parent / "outside") == [] and set(REPO.glob("rosbag2_*")) == before
    assert process.stop() == 0


# --- QoS override files -------------------------------------------------------------------------------------
def test_override_paths_outside_the_root_are_refused_alike(containers: Containers, root: pathlib.Path) -> None:
    """An existing, a secret and a missing file outside the root get one error: nothing is learnt about them."""
    outside = root.parent / "outside"
    (outside / "secret.yaml").write_text(f"/chatter: {{reliability: {SECRET}}}\n")
    process, client = containers.start("--bag-root", str(root))
    paths = ["/etc/shadow", str(outside / "secret.yaml"), str(outside / "missing.yaml"), "../outside/secret.yaml",
             "link/secret.yaml", "/nonexistent_dir/shadow"]
    errors = {path: refused_load(client, {"storage.uri": "bag", "record.qos_profile_overrides_path": path})
              for path in paths}
    for path, error in errors.items():
        assert QOS_PARAMETER in error and "outside the bag root" in error, error
        assert SECRET not in error and ":*:" not in error, error  # nor /etc/shadow's "root:*:..." entry
    assert len({error.replace(repr(path), "<path>") for path, error in errors.items()}) == 1, errors
    assert entries(root) == ["link"] and entries(outside) == ["secret.yaml"]
    assert process.stop() == 0
    assert SECRET not in process.output


OVERRIDE_FILES = {  # name: (content, the problem the error must name)
    "invalid_yaml": (f"topic: [{SECRET} unclosed\n", "not valid YAML"),
    "wrong_structure": (f"/chatter: {{reliability: {SECRET}}}\n", "entry 1 is not a valid QoS profile"),
    "unknown_key": (f"/chatter: {{{SECRET}: 1}}\n", "entry 1 is not a valid QoS profile"),
    "not_a_mapping": (f"- {SECRET}\n", "the file must map topic names to QoS profiles"),
    "too_large": (f"# {SECRET}\n" + "#" * (1024 * 1024) + "\n", "file larger than 1048576 bytes"),
    "directory": (None, "not a regular file"),
    "missing": ("", "file not found"),
}


@pytest.mark.parametrize("with_root", [True, False], ids=["bag_root", "no_bag_root"])
def test_override_file_errors_name_the_problem_and_disclose_nothing(containers: Containers, root: pathlib.Path,
                                                                    with_root: bool) -> None:
    process, client = containers.start(*(["--bag-root", str(root)] if with_root else []))
    for name, (content, problem) in OVERRIDE_FILES.items():
        path = root / name
        if content is None:
            path.mkdir()
        elif name != "missing":
            path.write_text(content)
        value = name if with_root else str(path)  # relative values resolve inside the root
        error = refused_load(client, {"storage.uri": str(root / f"bag_{name}"),
                                      "record.qos_profile_overrides_path": value})
        assert QOS_PARAMETER in error and problem in error, (name, error)
        assert SECRET not in error, (name, error)
        assert not (root / f"bag_{name}").exists()
    if not with_root:  # what issue #11 found: the first entry of /etc/shadow came back in the error
        error = refused_load(client, {"storage.uri": str(root / "bag_shadow"),
                                      "record.qos_profile_overrides_path": "/etc/shadow"})
        assert QOS_PARAMETER in error and ":*:" not in error and "daemon" not in error, error
    assert listing(client) == [] and process.alive()
    assert process.stop() == 0
    assert SECRET not in process.output


# --- the plugin allow-list ----------------------------------------------------------------------------------
def not_allowed(plugin: str) -> str:
    return f"{UNKNOWN_PLUGIN} Plugin '{plugin}' {NOT_ALLOWED} (--allow-plugins)"


def test_allow_list_refuses_other_plugins_alike(containers: Containers) -> None:
    process, client = containers.start("--allow-plugins", "components::T*", "--allow-plugins", "components::Listener")
    assert client.load(TALKER).success and client.load("components::Listener").success
    for plugin in ("components::Recorder", "components::DoesNotExist", MODULE_PLUGIN):
        refused = client.load(plugin, plugin.split(":")[0].split(".")[0])
        assert not refused.success and refused.error_message == not_allowed(plugin), refused
    assert [name for _, name in listing(client)] == ["/talker", "/listener"]
    assert process.stop() == 0


@pytest.mark.parametrize("flags, module_loads, talker_loads", [
    (["--allow-plugins", "*"], False, True),
    (["--allow-plugins", "tests.*"], False, False),
    (["--allow-module-plugins", "--allow-plugins", "components::*"], False, True),
    (["--allow-module-plugins", "--allow-plugins", "tests.container_test_plugins:*"], True, False),
], ids=["all_without_flag", "module_pattern_without_flag", "flag_pattern_misses", "flag_and_pattern"])
def test_module_plugins_need_the_flag_and_a_pattern(containers: Containers, flags: list[str], module_loads: bool,
                                                    talker_loads: bool) -> None:
    process, client = containers.start(*flags)
    module = client.load(MODULE_PLUGIN, "tests")
    assert module.success is module_loads, module
    if not module_loads:
        reason = NOT_ALLOWED if "--allow-module-plugins" in flags else "--allow-module-plugins"
        assert reason in module.error_message and module.error_message.startswith(UNKNOWN_PLUGIN), module
    talker = client.load(TALKER)
    assert talker.success is talker_loads, talker
    if not talker_loads:
        assert talker.error_message == not_allowed(TALKER)
    assert process.stop() == 0
