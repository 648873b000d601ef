"""``events/messages_lost`` (rosbag2 Rolling's MessagesLostEvent), from a real container to a plain subscriber.

A recorder whose disk hangs (tests/container_test_plugins.py HangingDiskRecorder) fills its cache and drops
camera frames: it must report them, per topic, as lost in the recorder. A healthy recorder next to it loses
nothing and must publish nothing.
"""
from __future__ import annotations

import time

from rclpy.node import Node
from rosbag2_interfaces.msg import MessagesLostEvent

from container_process import Containers, wait_until

PLUGINS = "tests.container_test_plugins"


def test_lost_messages_are_reported_live_and_only_then(containers: Containers, probe: Node, tmp_path) -> None:
    events: dict[str, list[MessagesLostEvent]] = {"/hanging": [], "/healthy": []}
    # A relative topic, as rosbag2's: both recorders publish on /events/messages_lost, node_name tells them apart
    probe.create_subscription(MessagesLostEvent, "/events/messages_lost",
                              lambda event: events.setdefault(event.node_name, []).append(event), 100)
    process, client = containers.start("--use-intra-process-comms", "--allow-module-plugins",
                                       "--shutdown-timeout", "2")
    assert client.load("components::CameraDriver", parameters={"width": 640, "height": 480}).success
    assert client.load("components::ImuDriver", parameters={"rate": 100.0}).success
    hanging = client.load(f"{PLUGINS}:HangingDiskRecorder", "tests", name="hanging", parameters={
        "storage.uri": str(tmp_path / "hanging"), "storage.max_cache_size": 4 * 1024 * 1024,
        "record.topics": ["/camera/image_raw"]})
    healthy = client.load("components::Recorder", name="healthy", parameters={
        "storage.uri": str(tmp_path / "healthy"), "record.topics": ["/imu/imu"]})
    assert hanging.success and healthy.success, (hanging, healthy)
    assert wait_until(lambda: len(events["/hanging"]) >= 2, 15.0, probe), "no loss event while frames are dropped"
    started = time.monotonic()
    first, later = events["/hanging"][0], events["/hanging"][-1]
    assert first.node_name == "/hanging"
    stats = {s.topic_name: s for s in first.messages_lost_statistics}
    assert set(stats) == {"/camera/image_raw"}  # topics without losses are left out
    assert stats["/camera/image_raw"].messages_lost_in_recorder > 0
    assert stats["/camera/image_raw"].messages_lost_in_transport == 0
    assert later.messages_lost_statistics[0].messages_lost_in_recorder > 0  # each event: the change only
    wait_until(lambda: False, 2.0, probe)
    span = time.monotonic() - started + 2.0
    assert len(events["/hanging"]) <= 2 + span * 1.0 + 1, "more than one event a second"
    assert events["/healthy"] == [], "a recorder that lost nothing published a loss event"
    process.stop()
