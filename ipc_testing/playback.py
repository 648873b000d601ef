"""``bag play`` run as a process, started paused and resumed once a subscriber of this process has matched.

A player that publishes before an external subscriber has matched loses the first messages (rosbag2 users pass
``--delay`` and hope discovery is done by then). Tests cannot hope: they start the player paused, wait for their
subscription to match its publisher, then call ``~/resume``.

That is the subscription's side of the match. The player's writer matches the subscription when the player's
participant has taken in the subscription's announcement, which a loaded machine can delay past the resume:
the first messages then went to no reader (fresh-clone run, Kilted: the first three of each of six bags). So
the topic is played transient-local (a QoS override file, as rosbag2 users give one) and the subscription asks
for it: a writer that matches late hands over what it already wrote, up to the subscription's depth.
"""
from __future__ import annotations

import copy
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbag2_interfaces.srv import Resume
from std_msgs.msg import String

from ipc_testing.calls import call, wait_until

RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


def no_earlier_publisher(probe: Node, topic: str, timeout: float = 30.0) -> None:
    """Wait until ``topic`` has no publisher in ``probe``'s graph, before a player is started whose match a test
    waits for: an earlier player that has exited can stay on the graph for a while, and a new subscription matches
    it at once, so the wait for a match would end before the new player is matched."""
    assert wait_until(lambda: probe.count_publishers(topic) == 0, timeout, probe), (
        f"{topic} still has a publisher before the player starts: {probe.get_publishers_info_by_topic(topic)}")


def play_to_the_end(probe: Node, command: Sequence[str | Path], topic: str = "/chatter",
                    env: dict[str, str] | None = None, cwd: Path | None = None,
                    qos: QoSProfile = RELIABLE) -> tuple[list[str], str]:
    """:func:`play` of ``std_msgs/String`` messages: the strings received, and the command's stdout."""
    got, stdout = play(probe, command, topic, String, env=env, cwd=cwd, qos=qos)
    return [message.data for message in got], stdout


def play(probe: Node, command: Sequence[str | Path], topic: str, msg_type: type, played_topic: str | None = None,
         env: dict[str, str] | None = None, cwd: Path | None = None,
         qos: QoSProfile = RELIABLE) -> tuple[list[Any], str]:
    """Run ``command`` (a ``bag play`` command line) with ``--start-paused`` and ``played_topic`` (the bag's topic
    that ``topic`` is published from: itself unless the player decodes it to ``topic``) played transient-local,
    resume it once ``probe``'s ``msg_type`` subscription of ``topic`` (``qos``, made transient-local: deep enough
    for the bursts the bag holds) has matched the player's publisher, and wait for its end.

    The player must be the topic's only publisher, so it waits first for earlier ones to leave the graph
    (:func:`no_earlier_publisher`): otherwise the new player's first messages could go to nobody.

    Returns the messages received and the command's stdout; AssertionError if it never matched or failed.
    """
    no_earlier_publisher(probe, topic)
    got: list[Any] = []
    qos = copy.copy(qos)
    qos.history, qos.durability = HistoryPolicy.KEEP_LAST, DurabilityPolicy.TRANSIENT_LOCAL
    subscription = probe.create_subscription(msg_type, topic, got.append, qos)
    resume = probe.create_client(Resume, "/rosbag2_player/resume")
    overrides = tempfile.NamedTemporaryFile("w", prefix="play_qos_", suffix=".yaml")  # noqa: SIM115
    try:
        profile = {"history": "keep_last", "depth": qos.depth, "reliability": "reliable",
                   "durability": "transient_local"}
        yaml.safe_dump({played_topic or topic: profile}, overrides)
        overrides.flush()
        process = subprocess.Popen([str(part) for part in command]
                                   + ["--start-paused", "--qos-profile-overrides-path", overrides.name],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=cwd)
        try:
            assert wait_until(lambda: subscription.get_publisher_count() > 0, 30.0, probe), "never matched"
            call(probe, resume, Resume.Request(), 30.0, again=True)
            # Spin while it plays: Fast DDS drops the samples of a writer that is gone before they were taken.
            wait_until(lambda: process.poll() is not None, 60.0, probe)
        finally:
            if process.poll() is None:
                process.kill()
        stdout, stderr = process.communicate(timeout=10)
        assert process.returncode == 0, stderr
        return got, stdout
    finally:
        overrides.close()
        probe.destroy_client(resume)
        probe.destroy_subscription(subscription)
