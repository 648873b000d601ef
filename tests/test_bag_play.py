"""``ipc-component bag play`` as users run it: a real process, its progress line on a terminal, its exit code.

The command runs a container with one ``components::Player`` in its own process; a plain rclpy subscription in
this process receives what it plays over Fast DDS.
"""
from __future__ import annotations

import json
import os
import pty
import select
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosbag2_interfaces.srv import PlayNext, Resume
from std_msgs.msg import String

from baglib.format.cdr_fast import serialize
from baglib.format.metadata import TopicInfo, qos_profile_dict
from baglib.write.writer import BagWriter
from container_process import call, wait_until
from ipc_testing import playback
from ipc_testing.held_participant import HELD, held_participant_library
from ipc_testing.process import run_command

CLI = str(Path(sys.executable).with_name("ipc-component"))
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
T0 = 1_700_000_000_000_000_000


def chatter_bag(path: Path, count: int, period_ms: int) -> Path:
    with BagWriter(path) as writer:
        writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String",
                                   offered_qos_profiles=[qos_profile_dict(RELIABLE)]))
        for n in range(count):
            t = T0 + n * period_ms * 1_000_000
            writer.write("/chatter", bytes(serialize(String(data=f"message {n}"))), t, t)
    return path


def play_to_the_end(probe: Node, *arguments: str) -> tuple[list[str], str]:
    """``bag play ARGUMENTS`` resumed once this process's /chatter subscription has matched the player's publisher
    (instead of a delay long enough for discovery); the strings received, and stdout."""
    return playback.play_to_the_end(probe, [CLI, "bag", "play", *arguments])


def test_plays_to_the_end_and_exits_zero(probe: Node, tmp_path: Path) -> None:
    bag = chatter_bag(tmp_path / "bag", 20, 50)
    # --delay (applied before the paused start) is exercised on the way
    got, stdout = play_to_the_end(probe, str(bag), "--delay", "0.2", "--rate", "2")
    assert got == [f"message {n}" for n in range(20)]
    assert stdout.splitlines()[-1].startswith("[FINISHED]  0.950 / 0.950 s  rate 2.00  20 msgs")
    assert "\r" not in stdout  # no progress line when stdout is not a terminal


def test_a_participant_that_never_finishes_its_destruction_does_not_hold_the_player(
        tmp_path: Path, tmp_path_factory: pytest.TempPathFactory) -> None:
    """Fast DDS's livelock at the end of ``bag play`` (ipc_testing.held_participant): the player's own container
    is torn down last and bounded like every command's; the playback's status and last line stand."""
    library = held_participant_library(tmp_path_factory.getbasetemp())
    result = run_command([CLI, "bag", "play", str(chatter_bag(tmp_path / "bag", 5, 10))], 60.0,
                         env=dict(os.environ, LD_PRELOAD=str(library)))
    assert result.returncode == 0, result
    assert result.stdout.splitlines()[-1].startswith("[FINISHED]  0.040 / 0.040 s"), result
    assert HELD in result.stderr and "Timeout" in result.stderr and "in destroy_node" in result.stderr, result


def test_a_subscription_matched_after_the_start_gets_every_message_of_a_topic_played_transient_local(
        probe: Node, tmp_path: Path) -> None:
    """What ``playback.play_to_the_end`` relies on: a topic played transient-local (a QoS override file) gives a
    subscription that matched only after the first messages went out (as when the player's writer takes in a
    subscription late) those messages too, in order. A volatile subscription created at the same moment gets
    only what came after."""
    bag = chatter_bag(tmp_path / "bag", 40, 50)  # 2 s: the late subscriptions match long before the end
    overrides = tmp_path / "qos.yaml"
    overrides.write_text("/chatter: {history: keep_last, depth: 40, reliability: reliable, "
                         "durability: transient_local}\n")
    playback.no_earlier_publisher(probe, "/chatter")
    early: list[String] = []
    probe.create_subscription(String, "/chatter", early.append, RELIABLE)
    resume = probe.create_client(Resume, "/rosbag2_player/resume")
    process = subprocess.Popen([CLI, "bag", "play", str(bag), "--start-paused", "--qos-profile-overrides-path",
                                str(overrides)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert wait_until(lambda: probe.count_publishers("/chatter") > 0, 30.0, probe), "no player"
        call(probe, resume, Resume.Request(), 30.0, again=True)
        assert wait_until(lambda: len(early) >= 5, 30.0, probe), early
        late: dict[str, list[String]] = {"transient_local": [], "volatile": []}
        for durability, got in late.items():
            qos = QoSProfile(depth=40, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if durability == "transient_local"
                             else DurabilityPolicy.VOLATILE)
            probe.create_subscription(String, "/chatter", got.append, qos)
        assert wait_until(lambda: process.poll() is not None, 60.0, probe)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.wait(timeout=10) == 0, process.stderr.read() if process.stderr else ""
    every = [f"message {n}" for n in range(40)]
    assert [m.data for m in late["transient_local"]] == every
    volatile = [m.data for m in late["volatile"]]
    assert volatile == every[len(every) - len(volatile):], volatile  # what came after it matched, in order
    assert "message 0" not in volatile, "the late volatile subscription should have missed the start"


def test_progress_line_on_a_terminal_and_ctrl_c(tmp_path: Path) -> None:
    bag = chatter_bag(tmp_path / "bag", 100, 100)  # 10 s
    controller, terminal = pty.openpty()
    process = subprocess.Popen([CLI, "bag", "play", str(bag), "--topics", "/chatter"],
                               stdout=terminal, stderr=subprocess.PIPE, text=False)
    os.close(terminal)
    output = b""
    try:
        deadline = time.monotonic() + 20
        while output.count(b"\r[PLAYING]") < 3 and time.monotonic() < deadline:
            if select.select([controller], [], [], 0.5)[0]:
                output += os.read(controller, 4096)
        assert output.count(b"\r[PLAYING]") >= 3, output
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=20) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        os.close(controller)
    assert b" / 9.900 s  rate 1.00" in output


def read_until(controller: int, done: Any, timeout: float = 20.0) -> bytes:
    """What the terminal shows until ``done(output)`` holds (or ``timeout`` passes)."""
    output = b""
    deadline = time.monotonic() + timeout
    while not done(output) and time.monotonic() < deadline:
        if select.select([controller], [], [], 0.5)[0]:
            output += os.read(controller, 4096)
    return output


def test_log_lines_never_share_the_progress_line(probe: Node, tmp_path: Path) -> None:
    # A user's terminal: stdout and stderr both on it. A play_next request while playing makes the player log a
    # warning (as rosbag2's does) while the progress line is drawn.
    bag = chatter_bag(tmp_path / "bag", 100, 100)  # 10 s
    controller, terminal = pty.openpty()
    process = subprocess.Popen([CLI, "bag", "play", str(bag), "--topics", "/chatter"], stdout=terminal,
                               stderr=terminal)
    os.close(terminal)
    play_next = probe.create_client(PlayNext, "/rosbag2_player/play_next")
    try:
        output = read_until(controller, lambda out: out.count(b"\r[PLAYING]") >= 2)
        assert output.count(b"\r[PLAYING]") >= 2, output
        assert not call(probe, play_next, PlayNext.Request(), 30.0, again=True).success
        output += read_until(controller, lambda out: b"\r[PLAYING]" in out.partition(b"Called play next")[2])
        playing = output  # what the terminal shows while playing (the logs of the shutdown clear the line)
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=20) == 0
    finally:
        probe.destroy_client(play_next)
        if process.poll() is None:
            process.kill()
            process.wait()
        os.close(controller)
    # what each terminal line ends up showing (the terminal sends "\r\n" for a newline)
    shown = [line.rstrip(b"\r").rsplit(b"\r", 1)[-1] for line in playing.split(b"\n")]
    warnings = [line for line in shown if b"Called play next" in line]
    assert warnings and all(b"[PLAYING]" not in line for line in warnings), output
    assert any(line.startswith(b"[PLAYING]") for line in shown), output


def test_a_bag_that_cannot_be_played_is_named(tmp_path: Path) -> None:
    result = subprocess.run([CLI, "bag", "play", str(tmp_path / "missing")], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 1
    assert f"Cannot play {tmp_path / 'missing'}" in result.stderr
    assert "missing" in result.stderr.splitlines()[-1]



def interleaved_bag(path: Path, index: int, count: int) -> Path:
    """Bag ``index`` of three: its /chatter messages every 30 ms, 10 ms after the previous bag's."""
    with BagWriter(path) as writer:
        writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String",
                                   offered_qos_profiles=[qos_profile_dict(RELIABLE)]))
        for n in range(count):
            t = T0 + (n * 30 + index * 10) * 1_000_000
            writer.write("/chatter", bytes(serialize(String(data=f"bag {index} message {n}"))), t, t)
    return path


@pytest.mark.parametrize("form", ["positional", "-i"])
def test_three_bags_play_as_one_timeline(probe: Node, tmp_path: Path, form: str) -> None:
    """What a subscriber of all three bags' topic receives is their merged order: bag 0, 1, 2, 0, 1, 2 ..."""
    bags = [str(interleaved_bag(tmp_path / f"bag{index}", index, 10)) for index in range(3)]
    named = bags if form == "positional" else ["-i", bags[0], "-i", bags[1], "mcap", "-i", bags[2]]
    got, stdout = play_to_the_end(probe, *named)
    assert got == [f"bag {index} message {n}" for n in range(10) for index in range(3)]
    assert stdout.splitlines()[-1].startswith("[FINISHED]  0.290 / 0.290 s  rate 1.00  30 msgs")


@pytest.mark.parametrize("arguments, message", [
    (["a", "-i", "b"], "do not mix"),
    ([], "name the bag to play"),
    (["-i", "a", "rosbag1"], "-i takes a bag and optionally its storage id"),
])
def test_bag_arguments_that_name_no_clear_set_of_bags_are_refused(arguments: list[str], message: str) -> None:
    result = subprocess.run([CLI, "bag", "play", *arguments], capture_output=True, text=True, timeout=60)
    assert result.returncode == 1 and message in result.stderr, result.stderr


def test_message_order_sent_plays_by_publish_time(probe: Node, tmp_path: Path) -> None:
    """``--message-order sent`` (rosbag2 Kilted #1876): messages received 0, 1, 2, ... but published in the
    opposite order within each pair reach a subscription in another process in publish order."""
    with BagWriter(tmp_path / "bag") as writer:
        writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String",
                                   offered_qos_profiles=[qos_profile_dict(RELIABLE)]))
        for n in range(10):
            received = T0 + n * 20_000_000
            published = received - (30_000_000 if n % 2 else 0)  # each odd one was sent before the even one
            writer.write("/chatter", bytes(serialize(String(data=f"message {n}"))), received, published)
    got, _ = play_to_the_end(probe, str(tmp_path / "bag"), "--message-order", "sent")
    assert got == [f"message {n ^ 1}" for n in range(10)]
    got, _ = play_to_the_end(probe, str(tmp_path / "bag"), "--message-order", "received")
    assert got == [f"message {n}" for n in range(10)]


# --- bag burst (ros2 bag burst) ---------------------------------------------------------------------------
HOUR_MS = 3_600_000  # messages an hour apart: played with their timing, a test would never see the second


@pytest.mark.parametrize("count, burst", [(3, 3), (0, 10)])
def test_burst_publishes_at_once_then_stays_paused(probe: Node, tmp_path: Path, count: int, burst: int) -> None:
    """``-n 3``: three of the bag's ten messages (an hour apart) out at once; ``-n 0`` (the default): all ten.
    Then the player stays paused in its run, its services answering, until Ctrl-C, as ``ros2 bag burst`` does
    (rosbag2's player does not end a run while paused, even at the end of the bag)."""
    from rosbag2_interfaces.srv import IsPaused
    from std_srvs.srv import Trigger

    stats = probe.create_client(Trigger, "/rosbag2_player/get_stats")
    is_paused = probe.create_client(IsPaused, "/rosbag2_player/is_paused")
    bag = chatter_bag(tmp_path / "bag", 10, HOUR_MS)
    process = subprocess.Popen([CLI, "bag", "burst", "-n", str(count), str(bag)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        def published() -> int:
            return sum(json.loads(call(probe, stats, timeout=30.0, again=True).message)["published"].values())

        assert wait_until(lambda: published() == burst, 60.0, probe), f"the burst did not publish {burst} messages"
        assert call(probe, is_paused, timeout=30.0, again=True).paused
        assert published() == burst and process.poll() is None
        process.send_signal(signal.SIGINT)
        _, stderr = process.communicate(timeout=60)
        assert process.returncode == 0, stderr
        assert f"Burst {burst} messages." in stderr, stderr
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
        probe.destroy_client(stats)
        probe.destroy_client(is_paused)


@pytest.mark.parametrize("arguments, message", [
    (["-n", "-1"], "argument -n/--num-messages: must not be negative, got -1"),
    (["-n", "two"], "argument -n/--num-messages: invalid int value: 'two'"),
    (["--start-offset", "-0.5"], "argument --start-offset: must not be negative, got -0.5"),
])
def test_burst_refuses_negative_counts_and_offsets(arguments: list[str], message: str,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    from ipc_component.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["bag", "burst", "bag", *arguments])
    assert message in capsys.readouterr().err
