"""What a user installs: the wheel built from a clean copy of the tree, installed non-editable.

An editable install finds every module in the source tree, so it cannot show a package that the wheel lacks (a
hand-written package list once left the player out). These tests look at the wheel itself and run the
installed commands from an environment that holds only the wheel (tests/installed.py).
"""
from __future__ import annotations

import signal
import subprocess
import tomllib
import zipfile
from pathlib import Path

import pytest
from rclpy.node import Node
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from installed import REPO, InstalledEnv
from ipc_testing.client import ContainerClient
from ipc_testing.playback import play_to_the_end
from ipc_testing.s3_server import S3Server

#: Folders of the tree that are not shipped: tests, benchmarks, examples (their own packages), the interface
#: sources (shipped as the generated packages) and docs.
NOT_SHIPPED = {"tests", "benchmarks", "examples", "srv", "docs", "build", "dist"}
#: What a plugin needs to load here: a bag to write, a bag to (fail to) read, a free port, a topic and codec.
PLUGIN_PARAMETERS = {"Recorder": {"storage.uri": "bag"}, "Player": {"storage.uri": "missing_bag"},
                     "FoxgloveBridge": {"port": 0},
                     # h264: the installed wheel's foxglove_msgs and PyAV's libx264 (opened at load)
                     "ImageEncoder": {"topics": ["/camera/image_raw"], "codec": "h264"}}
#: The plugin loaded and unloaded through the installed ``ipc-component`` (its parameters as the CLI takes them);
#: every plugin is loaded through LoadNode as well.
CLI_LOAD = ("components", "components::ImageEncoder", "-p", "topics:=[/camera/image_raw]", "-p", "codec:=h264")


def source_package_folders() -> set[str]:
    """Every folder of the source tree that holds Python modules, as a dotted package name."""
    found = set()
    for path in REPO.rglob("*.py"):
        parts = path.relative_to(REPO).parts[:-1]
        if parts and parts[0] not in NOT_SHIPPED and not any(p.startswith(".") or p == "__pycache__"
                                                             for p in parts):
            found.add(".".join(parts))
    return found


def wheel_packages(wheel: Path) -> set[str]:
    with zipfile.ZipFile(wheel) as archive:
        return {".".join(Path(name).parts[:-1]) for name in archive.namelist()
                if name.endswith(".py") and ".dist-info" not in name and ".data/" not in name}


def registered_plugins() -> dict[str, str]:
    """The ``rclpy_components`` entry points, read from pyproject.toml (not from the code under test)."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    return project["entry-points"]["rclpy_components"]


def the_wheel(env: InstalledEnv) -> Path:
    return next((env.root.parent / "wheels").glob("*.whl"))


def test_every_package_folder_of_the_tree_is_in_the_wheel(installed_env: InstalledEnv) -> None:
    in_wheel = wheel_packages(the_wheel(installed_env))
    expected = source_package_folders()
    assert {"components.player", "components.recorder", "baglib.read", "ipc_component"} <= expected
    assert expected - in_wheel == set()
    assert {"composition_interfaces.srv", "rosbag2_interfaces.srv", "foxglove_msgs.msg"} <= in_wheel  # generated


def test_the_rule_sees_a_missing_folder(tmp_path: Path) -> None:
    """The comparison above fails for a wheel that lacks a folder of the tree."""
    wheel = tmp_path / "partial-0-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as archive:
        for package in source_package_folders() - {"components.player"}:
            archive.writestr(package.replace(".", "/") + "/__init__.py", "")
    assert source_package_folders() - wheel_packages(wheel) == {"components.player"}


def test_installed_commands_and_modules_come_from_the_wheel(installed_env: InstalledEnv) -> None:
    site = installed_env.run(installed_env.python, "-c",
                             "import components.player.player as p, ipc_component.cli as c; "
                             "print(p.__file__); print(c.__file__)")
    assert site.returncode == 0, site.stderr
    assert all(line.startswith(str(installed_env.root)) for line in site.stdout.split()), site.stdout
    help_text = installed_env.run(installed_env.script("ipc-component"), "bag", "play", "--help")
    assert help_text.returncode == 0, help_text.stderr
    assert "usage: ipc-component bag play" in help_text.stdout


@pytest.mark.long
def test_installed_container_loads_every_registered_plugin(installed_env: InstalledEnv, probe: Node) -> None:
    container = subprocess.Popen([str(installed_env.python), "-m", "component_container", "--bag-root",
                                  str(installed_env.root), "--ros-args", "-r", "__node:=installed"],
                                 cwd=installed_env.root, env=installed_env.env(), stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True)
    cli = installed_env.script("ipc-component")
    client = ContainerClient(probe, "/installed")
    try:
        types = installed_env.run(cli, "types")
        assert types.returncode == 0, types.stderr
        listed = {line.strip() for line in types.stdout.splitlines()}
        assert set(registered_plugins()) <= listed
        by_cli = installed_env.run(cli, "load", "/installed", *CLI_LOAD, "-n", "by_cli")
        assert by_cli.stdout.startswith("Loaded component"), (by_cli.stdout, by_cli.stderr)
        unloaded = installed_env.run(cli, "unload", "/installed", by_cli.stdout.split()[2])
        assert unloaded.returncode == 0, unloaded.stderr
        client.wait()
        for n, (plugin, target) in enumerate(sorted(registered_plugins().items()), start=1):
            package = target.split(".")[0]  # rclcpp_components' package: where the class is defined
            loaded = client.load(plugin, package, name=f"plugin_{n}",
                                 parameters=PLUGIN_PARAMETERS.get(plugin.split("::")[-1]))
            if "Player" in plugin:  # it loads its module and class, then refuses the missing bag by name
                assert not loaded.success and "missing_bag" in loaded.error_message, loaded.error_message
                continue
            assert loaded.success, (plugin, loaded.error_message)
            assert client.unload(loaded.unique_id).success, plugin
    finally:
        client.destroy()
        container.send_signal(signal.SIGINT)
        try:
            output = container.communicate(timeout=30)[0]
        except subprocess.TimeoutExpired:
            container.kill()
            output = container.communicate()[0]
    assert container.returncode == 0, output


def test_installed_bag_play_plays_a_bag_written_by_rosbags(installed_env: InstalledEnv, probe: Node,
                                                          tmp_path: Path) -> None:
    typestore = get_typestore(Stores.ROS2_JAZZY)
    bag = tmp_path / "from_rosbags"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/installed_chatter", "std_msgs/msg/String", typestore=typestore)
        for n in range(10):
            data = typestore.serialize_cdr(typestore.types["std_msgs/msg/String"](data=f"m{n}"),
                                           "std_msgs/msg/String")
            writer.write(connection, 1_700_000_000_000_000_000 + n * 10_000_000, data)
    # --delay is applied before the paused start: exercised on the way
    got, _ = play_to_the_end(probe, [installed_env.script("ipc-component"), "bag", "play", bag, "--delay", "0.2"],
                             "/installed_chatter", env=installed_env.env(), cwd=installed_env.root)
    assert got == [f"m{n}" for n in range(10)]


def test_installed_bag_upload_sends_a_bag_that_rosbags_reads_back(installed_env: InstalledEnv, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """``ipc-component bag upload`` of the installed wheel (baglib.upload, its worker's modules) against a real
    nanio server: the bag in the store, downloaded by the test's own boto3 client, opens in rosbags whole."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    bag = tmp_path / "to_upload"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection("/uploaded", "std_msgs/msg/String", typestore=typestore)
        for n in range(10):
            writer.write(connection, 1_700_000_000_000_000_000 + n,
                         typestore.serialize_cdr(typestore.types["std_msgs/msg/String"](data=f"m{n}"),
                                                 "std_msgs/msg/String"))
    with S3Server(tmp_path / "store") as server:
        for name, value in server.env().items():
            monkeypatch.setenv(name, value)
        server.client().create_bucket(Bucket="bags")
        done = installed_env.run(installed_env.script("ipc-component"), "bag", "upload", bag, "s3://bags/fleet",
                                 "--endpoint-url", server.endpoint_url)
        assert done.returncode == 0 and "Uploaded 2 files" in done.stdout, done.stdout + done.stderr
        copy = tmp_path / "downloaded" / "to_upload"
        copy.mkdir(parents=True)
        for path in bag.iterdir():
            (copy / path.name).write_bytes(
                server.client().get_object(Bucket="bags", Key=f"fleet/to_upload/{path.name}")["Body"].read())
    with Reader(copy) as reader:
        assert [typestore.deserialize_cdr(data, "std_msgs/msg/String").data
                for _, _, data in reader.messages()] == [f"m{n}" for n in range(10)]
