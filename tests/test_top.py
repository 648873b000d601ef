"""``ipc-component top``: the S1 rig's drivers and a recorder in a real container, seen through its /diagnostics.

The rig is S1's (two cameras at 30 fps, a LiDAR at 10 Hz, an IMU at 200 Hz, a recorder) with small frames; one more
IMU runs without intra-process, so that the plain rclpy publisher path is counted too. ``top --once`` runs as a
user runs it (its own process, output to a pipe: not a terminal); the live view runs in a tmux pane.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image, Imu

from component_container.component_node import ComponentNode
from component_container.intra_process import IntraProcessManager
from component_container.publish_counts import PublishCounter, parse_publication, publication_values
from ipc_component.top_view import ContainerView, Report, Status, parse_reports, topic_rate
from ipc_testing import ContainerClient, ContainerProcess, wait_until
from test_cli import ours

REPO = Path(__file__).resolve().parents[1]
CONTAINER = "/top_rig"
#: Every component of the rig, the topics it publishes, and their nominal rates (Hz).
NOMINAL = {
    "/front_camera": {"/front_camera/image_raw": 30.0, "/front_camera/camera_info": 30.0},
    "/rear_camera": {"/rear_camera/image_raw": 30.0, "/rear_camera/camera_info": 30.0},
    "/lidar": {"/lidar/points": 10.0},
    "/imu": {"/imu/imu": 200.0},
    "/imu_dds": {"/imu_dds/imu": 200.0},
    "/recorder": {"/events/messages_lost": 0.0, "/events/write_split": 0.0},
}
TOLERANCE = 0.10


def rig_file(bag: Path) -> dict:
    ipc = {"use_intra_process_comms": True}
    camera = {"width": 320, "height": 240, "fps": 30.0}
    return {"components": [
        {"package": "components", "plugin": "components::CameraDriver", "name": "front_camera",
         "parameters": camera, "extra_arguments": ipc},
        {"package": "components", "plugin": "components::CameraDriver", "name": "rear_camera",
         "parameters": camera, "extra_arguments": ipc},
        {"package": "components", "plugin": "components::LidarDriver", "name": "lidar",
         "parameters": {"points_per_scan": 4096, "rate": 10.0}, "extra_arguments": ipc},
        {"package": "components", "plugin": "components::ImuDriver", "name": "imu",
         "parameters": {"rate": 200.0}, "extra_arguments": ipc},
        {"package": "components", "plugin": "components::ImuDriver", "name": "imu_dds", "parameters": {"rate": 200.0}},
        {"package": "components", "plugin": "components::Recorder", "name": "recorder", "extra_arguments": ipc,
         "parameters": {"record": {"all_topics": True, "exclude_regex": "^/(rosout|parameter_events|diagnostics)$"},
                        "storage": {"uri": str(bag)}}},
    ]}


@pytest.fixture(scope="module")
def rig(ros: None, tmp_path_factory: pytest.TempPathFactory) -> Iterator[ContainerProcess]:
    root = tmp_path_factory.mktemp("top")
    (root / "rig.yaml").write_text(yaml.safe_dump(rig_file(root / "bag")))
    node = Node("top_test_client")
    with ContainerProcess("--load", str(root / "rig.yaml"), name=CONTAINER, cwd=REPO) as process:
        client = ContainerClient(node, CONTAINER)
        try:
            client.wait(timeout=30.0)
            assert wait_until(lambda: len(client.listing()) == len(NOMINAL), 30.0), process.output[-3000:]
            yield process
        finally:
            client.destroy()
            node.destroy_node()
            assert process.stop() == 0, process.output[-3000:]


def top(*args: str, timeout: float = 30.0, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ipc_component.cli", "top", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO, env=dict(os.environ, **(env or {})))


def table(lines: list[str]) -> list[dict[str, str]]:
    """The rows of one container's table, as {column: cell}; columns are cut at the header's positions."""
    header = lines[0]
    starts = [match.start() for match in re.finditer(r"\S+(?: \S+)*", header)]
    names = [header[start:end].strip() for start, end in zip(starts, [*starts[1:], None])]
    return [{name: row[start:end].strip() for name, start, end in zip(names, starts, [*starts[1:], None])}
            for row in lines[1:]]


def components_of(output: str) -> dict[str, dict]:
    """``top --once`` output of one container: component -> its row, with ``topics``: topic -> (rate, bandwidth)."""
    rows = table(output.splitlines()[1:])
    components: dict[str, dict] = {}
    current: dict = {}
    for row in rows:
        if row["COMPONENT"]:
            current = components[row["COMPONENT"]] = {**row, "topics": {}}
        current["topics"][row["TOPIC"]] = (row["RATE (Hz)"], row["BANDWIDTH"])
    return components


def off_nominal(output: str) -> list[str]:
    """What of the rig ``top`` output does not show at its nominal rate (empty: everything does)."""
    components = components_of(output)
    wrong = [f"components {sorted(components)}"] if set(components) != set(NOMINAL) else []
    for name, topics in NOMINAL.items():
        shown = components.get(name, {}).get("topics", {})
        if set(shown) != set(topics):
            wrong.append(f"{name}: topics {sorted(shown)}")
            continue
        for topic, nominal in topics.items():
            rate = shown[topic][0]
            if rate == "-" or abs(float(rate) - nominal) > TOLERANCE * nominal:
                wrong.append(f"{topic}: {rate} Hz, nominal {nominal:g}")
    return wrong


def test_top_once_shows_the_rig_at_its_nominal_rates(rig: ContainerProcess) -> None:
    runs: list[subprocess.CompletedProcess] = []

    def nominal() -> bool:
        runs.append(top(CONTAINER, "--once"))
        assert runs[-1].returncode == 0, runs[-1].stderr
        return not off_nominal(runs[-1].stdout)

    # A busy machine may make a driver skip frames for a moment: wait until one snapshot shows every rate.
    assert wait_until(nominal, 60.0), (off_nominal(runs[-1].stdout), runs[-1].stdout)
    output = runs[-1].stdout
    heading = output.splitlines()[0]
    assert re.fullmatch(rf"{CONTAINER}  running  executor single  free disk [0-9.]+ [GM]B  up \d+ s", heading)
    components = components_of(output)
    recorder = components["/recorder"]
    assert recorder["STATUS"] == "recording"
    assert recorder["DROPS"].isdigit()
    assert re.fullmatch(r"[0-9.]+ [GM]B", recorder["FREE DISK"])
    for name in ("/front_camera", "/rear_camera", "/lidar", "/imu", "/imu_dds"):
        assert components[name]["DROPS"].isdigit(), components[name]  # frames skipped at the source
        assert components[name]["STATUS"] == "running"
    # the bandwidth is the rate times the message size: a 320 x 240 rgb8 image and its header
    rate, bandwidth = components["/front_camera"]["topics"]["/front_camera/image_raw"]
    value, unit = bandwidth.split()
    assert unit == "MB/s"
    assert float(value) * 1e6 / float(rate) == pytest.approx(320 * 240 * 3, rel=0.03)


def test_top_without_a_container_named_shows_every_container(rig: ContainerProcess) -> None:
    result = top("--once", "--spin-time", "3")  # a loaded machine may take its time to discover
    assert result.returncode == 0, result.stderr
    assert f"{CONTAINER}  " in result.stdout
    assert "/front_camera/image_raw" in result.stdout


def test_top_of_a_missing_container_fails() -> None:
    # Fast DDS writes its own errors to the same stderr (a shared-memory port that another process holds, when many
    # participants start at once, is one). A statistics topic it does not know is one that comes every time.
    result = top("/no_such_container", "--once", env={"FASTDDS_STATISTICS": "NO_SUCH_TOPIC"})
    assert result.returncode == 1
    assert "NO_SUCH_TOPIC is not a valid statistics topic" in result.stderr, result.stderr
    assert ours(result.stderr).splitlines() == [
        "Unable to find container node '/no_such_container'",
        f"    Searched ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST: a container "
        "started with other values is not seen, check them in both shells."]


class Tmux:
    """A tmux server of its own (its own socket), killed at the end."""

    def __init__(self) -> None:
        self.socket = f"top_test_{uuid.uuid4().hex[:8]}"

    def __call__(self, *args: str) -> str:
        return subprocess.run(["tmux", "-L", self.socket, *args], check=True, capture_output=True, text=True,
                              timeout=10).stdout

    def screen(self) -> str:
        return self("capture-pane", "-p", "-t", "top")

    def kill(self) -> None:
        subprocess.run(["tmux", "-L", self.socket, "kill-server"], capture_output=True, timeout=10)


@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed")
@pytest.mark.parametrize("key", ["q", "C-c"])
def test_live_view_in_a_terminal(rig: ContainerProcess, key: str, tmp_path: Path) -> None:
    tmux = Tmux()
    status = tmp_path / "status"
    command = (f"cd {REPO} && PYTHONPATH={os.environ.get('PYTHONPATH', '')} {sys.executable} -m ipc_component.cli "
               f"top {CONTAINER}; echo $? > {status}")
    try:
        tmux("new-session", "-d", "-s", "top", "-x", "150", "-y", "30", command, ";",
             "set-option", "-t", "top", "remain-on-exit", "on")
        assert wait_until(lambda: re.search(r"/imu/imu +\d", tmux.screen()), 30.0), tmux.screen()
        screen = tmux.screen()
        assert screen.startswith("ipc-component top  ")
        assert "(q: quit)" in screen.splitlines()[0]
        assert all(component in screen for component in NOMINAL)
        tmux("send-keys", "-t", "top", key)
        assert wait_until(lambda: status.exists() and status.read_text().strip(), 15.0), tmux.screen()
        assert status.read_text().strip() == "0"
        assert "/imu/imu" not in tmux.screen()  # the alternate screen was left: the shell's screen is back
    finally:
        tmux.kill()


# --- what the container counts, and how the view reads it -------------------------------------------------------
def test_every_publisher_of_a_component_counts_messages_and_serialized_bytes(ros: None) -> None:
    plain = ComponentNode("top_counting_plain")
    in_process = ComponentNode("top_counting_ipc", intra_process_manager=IntraProcessManager())
    try:
        for node in (plain, in_process):
            imu = node.create_publisher(Imu, "~/imu", 10)
            image = node.create_publisher(Image, "~/image", 10)
            sizes = 0
            for index in range(5):
                message = Image(height=index + 1, width=4, step=12, encoding="rgb8", data=bytes(12 * (index + 1)))
                image.publish(message)
                sizes += len(serialize_message(message))
                imu.publish(Imu())
            if node is plain:
                imu.publish(serialize_message(Imu()))  # rclpy publishes a serialized message as it is
            counts = {topic: counter.state for topic, counter in node.publish_counters()}
            name = node.get_fully_qualified_name()
            # rclpy's own /parameter_events publisher is not the component's
            assert set(counts) == {f"{name}/imu", f"{name}/image"}
            imus = 6 if node is plain else 5
            assert counts[f"{name}/imu"][:2] == (imus, imus * len(serialize_message(Imu())))
            assert counts[f"{name}/image"][:2] == (5, sizes)
    finally:
        plain.destroy_node()
        in_process.destroy_node()


class CountingComponent(ComponentNode):
    """A component whose own attributes have the names a counting base class might use for itself."""

    def __init__(self, **kwargs: object) -> None:
        super().__init__("top_own_names", **kwargs)
        self._count, self._counted, self._counted_publishers = 3, [], None
        self.publisher = self.create_publisher(Imu, "~/imu", 10)


@pytest.mark.parametrize("in_process", [False, True])
def test_a_component_s_own_attribute_names_do_not_break_counting(ros: None, in_process: bool) -> None:
    node = CountingComponent(intra_process_manager=IntraProcessManager() if in_process else None)
    try:
        node.publisher.publish(Imu())
        assert [(topic, counter.state[0]) for topic, counter in node.publish_counters()] == [("/top_own_names/imu", 1)]
    finally:
        node.destroy_node()


def test_counts_survive_the_trip_through_a_status() -> None:
    counter = PublishCounter()
    counter.count_bytes(100)
    counter.count_bytes(50)
    idle = PublishCounter()
    now = counter.state[2] + 250_000_000
    values = publication_values([("/a", counter), ("/b", idle), ("/a", idle)], now)
    assert values == {"published /a": "2 messages, 150 bytes, last 0.250000 s ago",
                      "published /b": "0 messages, 0 bytes"}
    parsed = dict(parse_publication(key, value) for key, value in values.items())
    assert (parsed["/a"].messages, parsed["/a"].bytes, parsed["/a"].age) == (2, 150, 0.25)
    assert parsed["/b"].age is None
    assert parse_publication("dropped", "3") is None


@pytest.mark.parametrize("phase", [0.0, 0.013, 0.05, 0.087, 0.099])
@pytest.mark.parametrize("interval", [0.96, 1.0, 1.04])
def test_a_rate_counts_whole_message_periods(phase: float, interval: float) -> None:
    """A 10 Hz topic read by reports at any phase: counting messages between the reports would say 9 to 11 Hz."""
    period = 0.1

    def published(at: float) -> tuple:
        count = int((at - phase) / period) + 1  # messages at phase, phase + period, ...
        last = phase + (count - 1) * period
        return parse_publication("published /t", f"{count} messages, {count * 10} bytes, last {at - last:.6f} s ago")[1]

    first, second = 5.0, 5.0 + interval
    rate = topic_rate(published(first), first, published(second), second)
    assert rate.hz == pytest.approx(10.0, rel=1e-3)
    assert rate.bytes_per_second == pytest.approx(100.0, rel=1e-3)


def test_rates_start_over_when_a_container_restarts() -> None:
    def report(uptime: float, messages: int) -> Report:
        status = Status(0, "running", {}, {"/t": parse_publication("published /t", f"{messages} messages, "
                                                                    f"{messages} bytes, last 0.0 s ago")[1]})
        return Report(uptime, Status(0, "running", {}), {"/c": status})

    view = ContainerView("/x")
    view.add(report(10.0, 100))
    view.add(report(11.0, 110))
    assert view.previous is not None
    view.add(report(0.5, 3))  # a new process under the same name
    assert view.previous is None


def test_reports_are_told_apart_by_container_and_other_publishers_ignored() -> None:
    def status(name: str, **values: str) -> DiagnosticStatus:
        return DiagnosticStatus(level=b"\x00", name=name, message="running",
                                values=[KeyValue(key=k, value=v) for k, v in values.items()])

    reports = parse_reports([
        status("/a: container", **{"uptime (s)": "12.5"}),
        status("/a: /cam", **{"published /cam/image": "3 messages, 30 bytes, last 0.1 s ago", "dropped": "2"}),
        status("/b: container"),                       # no uptime: not one of this project's containers
        status("motor driver: temperature"),
    ])
    assert list(reports) == ["/a"]
    assert reports["/a"].uptime == 12.5
    assert reports["/a"].components["/cam"].values == {"dropped": "2"}
    assert reports["/a"].components["/cam"].published["/cam/image"].messages == 3
