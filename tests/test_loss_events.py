"""``events/messages_lost`` (rosbag2 Rolling's MessagesLostEvent), from a real container to a plain subscriber.

A recorder whose disk hangs (tests/container_test_plugins.py HangingDiskRecorder) fills its cache and drops
camera frames: it must report them, per topic, as lost in the recorder, each event with the change since the
previous one (once the camera is gone, the events add up to the recorder's own count of its drops). A healthy
recorder next to it loses nothing and must publish nothing. The rate limit (at most one event a second) is a
matter of timing, not checked here.
"""
from __future__ import annotations

import json

from rclpy.node import Node
from rosbag2_interfaces.msg import MessagesLostEvent
from std_srvs.srv import Trigger

from container_process import Containers, call, wait_until

PLUGINS = "tests.container_test_plugins"


def test_lost_messages_are_reported_live_and_only_then(containers: Containers, probe: Node, tmp_path) -> None:
    events: dict[str, list[MessagesLostEvent]] = {"/hanging": [], "/healthy": []}
    # A relative topic, as rosbag2's: both recorders publish on /events/messages_lost, node_name tells them apart
    probe.create_subscription(MessagesLostEvent, "/events/messages_lost",
                              lambda event: events.setdefault(event.node_name, []).append(event), 100)
    process, client = containers.start("--use-intra-process-comms", "--allow-module-plugins",
                                       "--shutdown-timeout", "2")
    camera = client.load("components::CameraDriver", parameters={"width": 640, "height": 480})
    assert camera.success, camera
    assert client.load("components::ImuDriver", parameters={"rate": 100.0}).success
    hanging = client.load(f"{PLUGINS}:HangingDiskRecorder", "tests", name="hanging", parameters={
        "storage.uri": str(tmp_path / "hanging"), "storage.max_cache_size": 4 * 1024 * 1024,
        "storage.stall_reserve": 0,  # drop as soon as the cache is full (the reserve is test_stall_reserve's)
        "record.topics": ["/camera/image_raw"]})
    healthy = client.load("components::Recorder", name="healthy", parameters={
        "storage.uri": str(tmp_path / "healthy"), "record.topics": ["/imu/imu"]})
    assert hanging.success and healthy.success, (hanging, healthy)
    assert wait_until(lambda: len(events["/hanging"]) >= 2, 15.0, probe), "no loss event while frames are dropped"
    first, later = events["/hanging"][0], events["/hanging"][1]
    assert first.node_name == "/hanging"
    stats = {s.topic_name: s for s in first.messages_lost_statistics}
    assert set(stats) == {"/camera/image_raw"}  # topics without losses are left out
    assert stats["/camera/image_raw"].messages_lost_in_recorder > 0
    assert stats["/camera/image_raw"].messages_lost_in_transport == 0
    assert later.messages_lost_statistics[0].messages_lost_in_recorder > 0  # each event: the change only

    # No more frames: the events published so far and the last one to come add up to the recorder's own count.
    assert client.unload(camera.unique_id).success
    get_stats = probe.create_client(Trigger, "/hanging/get_stats")

    def dropped_in_recorder() -> int:
        reasons = json.loads(call(probe, get_stats, again=True).message)["current"]["drop_reasons"]
        return sum(n for reason, n in reasons.get("/camera/image_raw", {}).items() if reason != "queue_full")

    def reported() -> int:
        return sum(stat.messages_lost_in_recorder for event in events["/hanging"]
                   for stat in event.messages_lost_statistics if stat.topic_name == "/camera/image_raw")

    assert wait_until(lambda: reported() == dropped_in_recorder(), 20.0, probe), \
        (reported(), dropped_in_recorder(), len(events["/hanging"]))
    assert all(stat.messages_lost_in_recorder > 0 for event in events["/hanging"]
               for stat in event.messages_lost_statistics), "an event repeated no change"
    # both recorders' 1 s timers ran at least twice since the loads: a loss of the healthy one would be out
    assert events["/healthy"] == [], "a recorder that lost nothing published a loss event"
    probe.destroy_client(get_stats)
    process.stop()
