"""``components::FoxgloveBridge`` as users run it: a real container with the drivers (and a recorder), the bridge
loaded next to them, and Foxglove's own WebSocket client (``@foxglove/ws-protocol`` from npm, run with node:
tests/foxglove_client) decoding what it receives with Foxglove's ROS 2 CDR reader
(``@foxglove/rosmsg2-serialization``) and the schema the bridge advertised.

What the drivers publish is known: their sequence numbers (first 8 bytes of Image.data, Imu
``orientation_covariance[1]``) are consecutive, so a client that got every message sees a contiguous run.
"""
from __future__ import annotations

import base64
import json
import socket
import time
from pathlib import Path
from typing import Any, Iterator

import pytest
import yaml
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from std_srvs.srv import Trigger

from baglib.format.message_definitions import service_definitions
from components.foxglove_bridge.channel_queue import MAX_QUEUED_BYTES, ChannelQueue
from components.foxglove_bridge.video_feed import StampRateLimit

from container_process import recorder_stats
from ffmpeg_tools import probe_h264
from ipc_testing.foxglove_client import FoxgloveClient, bridge_url, gaps, install_client
from ipc_testing import ContainerClient, ContainerProcess, call, wait_until

REPO = Path(__file__).resolve().parents[1]
IPC = {"use_intra_process_comms": True}
CAMERA = "/camera/image_raw"
IMU = "/imu/imu"
EXT_IMU = "/ext_imu/imu"
VIDEO = f"{CAMERA}/video"


def rig_file(path: Path, components: list[tuple[str, str, dict[str, Any], bool]]) -> Path:
    path.write_text(yaml.safe_dump({"components": [
        {"package": "components", "plugin": plugin, "name": name, "parameters": parameters,
         "extra_arguments": {"use_intra_process_comms": ipc}} for plugin, name, parameters, ipc in components]}))
    return path


@pytest.fixture(scope="module")
def client_dir() -> Path:
    return install_client()


@pytest.fixture(scope="module")
def rig(ros: None, tmp_path_factory: pytest.TempPathFactory,
        client_dir: Path) -> Iterator[tuple[ContainerProcess, ContainerClient]]:
    """A container with a 640x480 30 Hz camera and a 200 Hz IMU (intra-process), and a second one with an IMU
    whose messages reach the bridge over DDS."""
    folder = tmp_path_factory.mktemp("foxglove_rig")
    drivers = rig_file(folder / "rig.yaml", [
        ("components::CameraDriver", "camera", {"width": 640, "height": 480, "fps": 30.0}, True),
        ("components::ImuDriver", "imu", {"rate": 200.0}, True)])
    external = rig_file(folder / "ext.yaml", [("components::ImuDriver", "ext_imu", {"rate": 50.0}, False)])
    node = Node("foxglove_rig_client")
    rig_process = ContainerProcess("--load", str(drivers), name="foxglove_rig", cwd=str(REPO))
    ext_process = ContainerProcess("--load", str(external), name="foxglove_ext", cwd=str(REPO))
    client = ContainerClient(node, rig_process.name)
    try:
        client.wait(timeout=30.0)
        yield rig_process, client
    finally:
        for process in (rig_process, ext_process):
            with process:
                if process.alive():
                    process.stop()
            print(f"--- output of {process.name}:\n{process.output}")
        client.destroy()
        node.destroy_node()


def load(client: ContainerClient, plugin: str, name: str, parameters: dict[str, Any]) -> int:
    response = client.load(plugin, name=name, parameters=parameters, extra=IPC)
    assert response.success, response.error_message
    return response.unique_id


def load_bridge(rig: tuple[ContainerProcess, ContainerClient], name: str = "foxglove_bridge",
                **parameters: Any) -> tuple[int, str]:
    """Load a bridge on a free port; returns its unique id and the URL it logged."""
    process, client = rig
    mark = len(process.output)
    unique_id = load(client, "components::FoxgloveBridge", name, {"port": 0, **parameters})
    assert wait_until(lambda: "Foxglove bridge listening" in process.output[mark:], 10.0), process.output[mark:]
    return unique_id, bridge_url(process.output[mark:])


def bridge_subscriptions(node: Node, topic: str, bridge: str = "foxglove_bridge") -> int:
    return sum(1 for info in node.get_subscriptions_info_by_topic(topic) if info.node_name == bridge)


def trigger_json(node: Node, service: str) -> dict[str, Any]:
    client = node.create_client(Trigger, service)
    try:
        return json.loads(call(node, client, Trigger.Request(), again=True).message)
    finally:
        node.destroy_client(client)


def assert_contiguous(sequences: list[int], label: str) -> None:
    assert sequences == sorted(sequences), f"{label}: out of order"
    assert gaps(sequences) == 0, f"{label}: {gaps(sequences)} missing in {sequences[0]}..{sequences[-1]}"


# --- the data path ----------------------------------------------------------------------------------------
def test_streams_in_process_and_dds_topics_and_subscribes_only_while_wanted(rig, probe: Node) -> None:
    """Camera and IMU in-process, an IMU of another process over DDS: every message, decoded by Foxglove's
    reader; the bridge's ROS subscription exists exactly while a client is subscribed to the channel."""
    unique_id, url = load_bridge(rig)
    try:
        assert wait_until(lambda: probe.get_publishers_info_by_topic(EXT_IMU), 20.0, probe)
        with FoxgloveClient(url) as client:
            client.wait_for("advertise", lambda e: any(c["topic"] == EXT_IMU for c in e["channels"]))
            channels = {c["topic"]: c for e in client.of("advertise") for c in e["channels"]}
            assert channels[CAMERA]["schemaName"] == "sensor_msgs/msg/Image"
            assert {(c["encoding"], c["schemaEncoding"]) for c in channels.values()} == {("cdr", "ros2msg")}
            assert bridge_subscriptions(probe, CAMERA) == 0  # nobody asked yet
            client.subscribe(CAMERA, IMU, EXT_IMU)
            for topic, count in ((CAMERA, 30), (IMU, 200)):
                assert_contiguous(client.wait_messages(topic, count), topic)
            # Over DDS the bridge is a subscriber like any other: a keep_last reader of depth 10 (the publisher's)
            # may lose samples while the container's executor is busy, so only the order is exact.
            external = client.wait_messages(EXT_IMU, 50)
            assert external == sorted(set(external))
            assert client.of("error") == []
            assert bridge_subscriptions(probe, CAMERA) == 1

            client.unsubscribe(CAMERA)
            assert wait_until(lambda: bridge_subscriptions(probe, CAMERA) == 0, 10.0, probe), "still subscribed"
            assert bridge_subscriptions(probe, IMU) == 1
        # the client disconnected: the bridge leaves every topic
        assert wait_until(lambda: bridge_subscriptions(probe, IMU) + bridge_subscriptions(probe, EXT_IMU) == 0,
                          10.0, probe)
    finally:
        assert rig[1].unload(unique_id).success


@pytest.mark.parametrize("offered, chosen", [
    ((), "foxglove.websocket.v1"),  # @foxglove/ws-protocol as it ships, Lichtblick, Foxglove before the SDK
    (("foxglove.sdk.v1",), "foxglove.sdk.v1"),  # clients of the Foxglove SDK
    (("foxglove.websocket.v1", "foxglove.sdk.v1"), "foxglove.sdk.v1"),  # the Foxglove app offers both
])
def test_clients_of_either_protocol_name_get_the_same_frames(rig, offered: tuple[str, ...], chosen: str) -> None:
    """A client offering only the older subprotocol name connects (the SDK's server alone answers it HTTP 400);
    next to a client of the SDK's name it decodes the same camera frames."""
    unique_id, url = load_bridge(rig)
    try:
        with FoxgloveClient(url, offered) as client, FoxgloveClient(url, ["foxglove.sdk.v1"]) as reference:
            assert client.wait_for("open")["protocol"] == chosen
            for each in (client, reference):
                each.subscribe(CAMERA)
            reference.wait_messages(CAMERA, 1)
            first = reference.sequences(CAMERA)[0]
            client.wait_for("message", lambda e: e["sequence"] >= first + 30)
            reference.wait_for("message", lambda e: e["sequence"] >= first + 30)
            for each in (client, reference):
                assert_contiguous(each.sequences(CAMERA), CAMERA)
            sizes = {e["size"] for each in (client, reference) for e in each.of("message")}
            assert len(sizes) == 1 and sizes.pop() > 640 * 480 * 3, "the frames differ between the clients"
            assert client.of("error") == [] and reference.of("error") == []
    finally:
        assert rig[1].unload(unique_id).success


def test_a_client_offering_neither_name_gets_the_servers_refusal(rig) -> None:
    unique_id, url = load_bridge(rig)
    try:
        host, port = url.removeprefix("ws://").rsplit(":", 1)
        with socket.create_connection((host, int(port)), timeout=10.0) as connection:
            connection.sendall(b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                               b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
                               b"Sec-WebSocket-Protocol: something.else\r\n\r\n")
            answer = b""
            while chunk := connection.recv(4096):
                answer += chunk
        assert answer.startswith(b"HTTP/1.1 400") and b"Missing expected sec-websocket-protocol" in answer, answer
    finally:
        assert rig[1].unload(unique_id).success


def test_a_stalled_client_costs_the_recorder_and_the_other_client_nothing(rig, probe: Node, tmp_path: Path) -> None:
    """Client A stops reading (SIGSTOP) for five seconds while B watches the same camera and IMU and a
    recorder records them: B's runs stay contiguous, the recorder drops nothing, the bridge's own queues drop
    nothing; what A missed is the difference between what the bridge handed to its outbox and what it got.

    Each client's outbox holds 256 messages (about 1.1 s of the camera and IMU together): B reads in this test
    process, which a loaded machine can pause for longer than the default 32 messages last (0.14 s; B once lost
    4 frames so, in a full suite run); A's five seconds (about 1150 messages) overflow it either way."""
    process, container = rig
    recorder = load(container, "components::Recorder", "recorder",
                    {"record.topics": [CAMERA, IMU], "storage.uri": str(tmp_path / "bag")})
    unique_id, url = load_bridge(rig, message_backlog_size=256)
    try:
        with FoxgloveClient(url) as stalled, FoxgloveClient(url) as watcher:
            for client in (stalled, watcher):
                client.subscribe(CAMERA, IMU)
                client.wait_messages(CAMERA, 5)
            stalled.pause()
            start = len(watcher.sequences(CAMERA))
            watcher.wait_messages(CAMERA, start + 150, timeout=30.0)  # five seconds of frames
            stalled.resume()
            last = watcher.sequences(CAMERA)[-1]
            assert wait_until(lambda: stalled.sequences(CAMERA) and stalled.sequences(CAMERA)[-1] >= last, 20.0)
            watcher_camera, watcher_imu = watcher.sequences(CAMERA), watcher.sequences(IMU)
            stalled_camera = stalled.sequences(CAMERA)
            stats = trigger_json(probe, "/foxglove_bridge/get_stats")["channels"]
        assert_contiguous(watcher_camera, "watcher camera")
        assert_contiguous(watcher_imu, "watcher imu")
        assert gaps(stalled_camera) > 0, "the stalled client lost nothing: it did not stall long enough"
        for topic in (CAMERA, IMU):
            assert stats[topic]["dropped"] == 0, stats[topic]
        handed = stats[CAMERA]["sent_to"]
        assert len(handed) == 2 and len(set(handed.values())) <= 2
        counts = recorder_stats(probe, "/recorder")["current"]["topics"]
        for topic in (CAMERA, IMU):
            assert counts[topic]["dropped"] == 0 and counts[topic]["queue_dropped"] == 0, counts[topic]
            assert counts[topic]["received"] > 0
    finally:
        assert container.unload(unique_id).success
        assert container.unload(recorder).success


def test_rate_limit_and_topic_whitelist(rig, probe: Node) -> None:
    unique_id, url = load_bridge(rig, topic_whitelist=["/camera/.*", IMU], rate_limits=[".*/image_raw=5"])
    try:
        with FoxgloveClient(url) as client:
            client.wait_for("advertise", lambda e: any(c["topic"] == IMU for c in e["channels"]))
            topics = {c["topic"] for e in client.of("advertise") for c in e["channels"]}
            assert topics == {CAMERA, "/camera/camera_info", IMU, VIDEO}
            client.subscribe(CAMERA, IMU)
            client.wait_messages(CAMERA, 2)
            began, first = time.monotonic(), len(client.sequences(CAMERA))
            imu = client.wait_messages(IMU, len(client.sequences(IMU)) + 400)  # two seconds at full rate
            frames = len(client.sequences(CAMERA)) - first
            assert frames <= 5 * (time.monotonic() - began) + 1, frames
            assert_contiguous(imu, "imu")
            stats = trigger_json(probe, "/foxglove_bridge/get_stats")["channels"]
            assert stats[CAMERA]["throttled"] > 0 and stats[IMU]["throttled"] == 0
    finally:
        assert rig[1].unload(unique_id).success


# --- video channels -----------------------------------------------------------------------------------------
def video_payloads(client: FoxgloveClient) -> list[bytes]:
    return [base64.b64decode(e["data"]) for e in client.of("message", lambda e: e["topic"] == VIDEO)]


def is_keyframe(payload: bytes) -> bool:
    """Whether ffprobe reads one access unit as a keyframe (with its parameter sets: it decodes on its own)."""
    return any("K" in packet["flags"] for packet in probe_h264(payload)["packets"])


def test_video_channel_is_h264_at_the_configured_width_and_rate_encoded_only_while_watched(
        rig, probe: Node, tmp_path: Path) -> None:
    """The camera (640x480, 30 Hz) as H.264 video: nothing encoded before a client subscribes; the subscriber's
    payloads, concatenated, decode with ffprobe at 320 px wide, starting at a keyframe, at most 10 frames per
    second of the messages' stamps; a client joining later gets a keyframe at once; after the unsubscribe no
    message reaches the client and nothing is encoded; the recorder beside it loses nothing."""
    process, container = rig
    recorder = load(container, "components::Recorder", "video_recorder",
                    {"record.topics": [CAMERA], "storage.uri": str(tmp_path / "bag")})
    unique_id, url = load_bridge(rig, **{"video.max_width": 320, "video.max_rate": 10.0})

    def camera_received() -> int:
        return recorder_stats(probe, "/video_recorder")["current"]["topics"].get(CAMERA, {}).get("received", 0)

    def video_stats() -> dict[str, Any]:
        return trigger_json(probe, "/foxglove_bridge/get_stats")["channels"].get(VIDEO, {})

    def camera_advances() -> None:
        """A second of camera frames reaches the recorder (the condition the idle checks wait on)."""
        start = camera_received()
        assert wait_until(lambda: camera_received() >= start + 30, 20.0), "the camera stopped"

    try:
        with FoxgloveClient(url) as viewer:
            advertised = viewer.wait_for("advertise", lambda e: any(c["topic"] == VIDEO for c in e["channels"]))
            channel = next(c for c in advertised["channels"] if c["topic"] == VIDEO)
            assert (channel["schemaName"], channel["encoding"], channel["schemaEncoding"]) == (
                "foxglove_msgs/msg/CompressedVideo", "cdr", "ros2msg")
            camera_advances()
            assert video_stats() == {} and bridge_subscriptions(probe, CAMERA) == 0, "encoding without a client"

            viewer.subscribe(VIDEO)
            assert wait_until(lambda: len(video_payloads(viewer)) >= 20, 30.0), viewer.events[-3:]
            events = viewer.of("message", lambda e: e["topic"] == VIDEO)
            payloads = video_payloads(viewer)
            report = probe_h264(b"".join(payloads))
            assert (report["stream"]["width"], report["stream"]["height"]) == (320, 240)
            assert int(report["stream"]["nb_read_frames"]) == len(payloads) and report["errors"] == ""
            assert len(report["packets"]) == len(payloads) and "K" in report["packets"][0]["flags"]
            assert {e["format"] for e in events} == {"h264"}
            stamps = [sec * 10**9 + nanosec for sec, nanosec in (e["stamp"] for e in events)]
            assert stamps == sorted(set(stamps))
            assert (len(stamps) - 1) * 100_000_000 <= stamps[-1] - stamps[0], "more than 10 frames a second"

            with FoxgloveClient(url) as late:
                late.subscribe(VIDEO)
                assert wait_until(lambda: len(video_payloads(late)) >= 3, 20.0), late.events[-3:]
                joined = video_payloads(late)
            # The SDK enrols a client before it tells the bridge: a frame sent in between may come first, and
            # the keyframe the bridge asks for then follows at once.
            first_key = next(i for i, payload in enumerate(joined) if is_keyframe(payload))
            assert first_key <= 1, [is_keyframe(payload) for payload in joined]
            assert int(probe_h264(b"".join(joined[first_key:]))["stream"]["nb_read_frames"]) == len(joined) - first_key

            viewer.unsubscribe(VIDEO)
            assert wait_until(lambda: bridge_subscriptions(probe, CAMERA) == 0, 10.0, probe), "still subscribed"
            assert wait_until(lambda: video_stats()["clients"] == [], 10.0)
            before, strays = video_stats(), len(viewer.of("stray"))
            assert before["encoder"]["running"] == 0
            camera_advances()
            after = video_stats()
            assert (after["sent"], after["encoder"]) == (before["sent"], before["encoder"]), "encoded unwatched"
            assert len(viewer.of("stray")) == strays, "messages after the unsubscribe"
            assert before["dropped"] == before["encoder"]["skipped"] + before["encoder"]["rejected"]
            assert viewer.of("error") == []
        counts = recorder_stats(probe, "/video_recorder")["current"]["topics"][CAMERA]
        assert counts["dropped"] == 0 and counts["queue_dropped"] == 0 and counts["received"] > 0, counts
    finally:
        assert container.unload(unique_id).success
        assert container.unload(recorder).success


def test_stamp_rate_limit_admits_at_most_the_rate_and_restarts_when_stamps_go_back() -> None:
    limit = StampRateLimit(10.0)
    period = 33_333_333  # a 30 Hz camera
    admitted = [i for i in range(300) if limit.admit(10**9 + i * period)]
    assert 90 <= len(admitted) <= 100 and all(b - a >= 3 for a, b in zip(admitted, admitted[1:]))
    assert limit.admit(10**9)  # a bag played again from its start
    assert not limit.admit(10**9 + period)


# --- parameters, graph, time ------------------------------------------------------------------------------
def test_parameters_and_connection_graph(rig, probe: Node) -> None:
    unique_id, url = load_bridge(rig)
    try:
        with FoxgloveClient(url) as client:
            client.wait_for("serverInfo")
            assert {"parameters", "connectionGraph"} <= set(client.of("serverInfo")[0]["capabilities"])
            client.send(op="getParameters", names=["/camera.fps", "/imu.rate"], id="get")
            answer = client.wait_for("parameterValues", lambda e: e["id"] == "get")
            values = {p["name"]: p for p in answer["parameters"]}
            assert values["/camera.fps"]["value"] == 30 and values["/camera.fps"]["type"] == "float64"
            assert values["/imu.rate"]["value"] == 200

            client.send(op="setParameters", parameters=[{"name": "/camera.frame_id", "value": "front"}], id="set")
            answer = client.wait_for("parameterValues", lambda e: e["id"] == "set")["parameters"]
            assert answer == [{"name": "/camera.frame_id", "value": "front"}]
            assert ros_parameter(probe, "/camera", "frame_id") == "front"

            client.send(op="getParameters", names=[], id="all")
            names = {p["name"] for p in client.wait_for("parameterValues", lambda e: e["id"] == "all")["parameters"]}
            assert {"/camera.width", "/imu.rate", "/foxglove_bridge.port"} <= names

            client.subscribe(IMU)
            client.send(op="subscribeConnectionGraph")
            graph = client.wait_for("connectionGraph", lambda e: any(
                t["name"] == IMU and "/foxglove_bridge" in t["subscriberIds"] for t in e["subscribedTopics"]))
            assert graph is not None
            published = {t["name"]: t["publisherIds"] for e in client.of("connectionGraph")
                         for t in e["publishedTopics"]}
            assert published[CAMERA] == ["/camera"]
    finally:
        assert rig[1].unload(unique_id).success


def test_services_are_called_with_cdr(rig) -> None:
    """A ROS service of the graph, called from Foxglove's client: the request encoded and the response decoded
    by Foxglove's CDR writer and reader with the definitions the bridge advertised."""
    unique_id, url = load_bridge(rig, service_whitelist=["/camera/.*"])
    try:
        with FoxgloveClient(url) as client:
            client.wait_for("advertiseServices", lambda e: any(s["name"] == "/camera/get_parameters"
                                                                  for s in e["services"]))
            offered = {s["name"]: s["type"] for e in client.of("advertiseServices") for s in e["services"]}
            assert offered["/camera/get_parameters"] == "rcl_interfaces/srv/GetParameters"
            assert all(name.startswith("/camera/") for name in offered)
            client.send(op="callService", service="/camera/get_parameters", request={"names": ["fps", "width"]},
                        callId=7)
            response = client.wait_for("serviceResponse", lambda e: e["callId"] == 7)["response"]
            assert [(v["type"], v["double_value"], v["integer_value"]) for v in response["values"]] == [
                (3, 30.0, 0), (2, 0.0, 640)]
            assert client.of("serviceFailure") == []
    finally:
        assert rig[1].unload(unique_id).success


def ros_parameter(node: Node, target: str, name: str) -> Any:
    client = node.create_client(GetParameters, f"{target}/get_parameters")
    try:
        return call(node, client, GetParameters.Request(names=[name]), again=True).values[0].string_value
    finally:
        node.destroy_client(client)


def test_param_whitelist_limits_what_clients_see(rig) -> None:
    unique_id, url = load_bridge(rig, param_whitelist=[r"/camera\..*"])
    try:
        with FoxgloveClient(url) as client:
            client.send(op="getParameters", names=[], id="all")
            names = {p["name"] for p in client.wait_for("parameterValues", lambda e: e["id"] == "all")["parameters"]}
            assert names and all(name.startswith("/camera.") for name in names), names
            client.send(op="setParameters", parameters=[{"name": "/imu.rate", "value": 10.0}], id="set")
            assert client.wait_for("parameterValues", lambda e: e["id"] == "set")["parameters"] == []
    finally:
        assert rig[1].unload(unique_id).success


def test_sim_time_sends_clock_as_server_time(rig, probe: Node) -> None:
    unique_id, url = load_bridge(rig, use_sim_time=True)
    publisher = probe.create_publisher(Clock, "/clock", 10)
    try:
        with FoxgloveClient(url) as client:
            assert "time" in client.wait_for("serverInfo")["capabilities"]
            stamp = Clock()
            stamp.clock.sec, stamp.clock.nanosec = 1234, 500_000_000

            def got_time() -> bool:
                publisher.publish(stamp)
                return bool(client.of("time", lambda e: e["timestamp"] == 1_234_500_000_000))
            assert wait_until(got_time, 20.0, interval=0.1)
    finally:
        probe.destroy_publisher(publisher)
        assert rig[1].unload(unique_id).success


# --- what is refused ----------------------------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as probe_socket:
        probe_socket.bind(("127.0.0.1", 0))
        return probe_socket.getsockname()[1]


@pytest.mark.parametrize("parameters, message", [
    ({"port": 70000}, "parameter 'port' must be in [0, 65535]"),
    ({"address": "example.com"}, "parameter 'address' must be an IPv4 or IPv6 address"),
    ({"rate_limits": ["camera"]}, "parameter 'rate_limits' entries must be 'REGEX=HZ'"),
    ({"rate_limits": [".*=0"]}, "must be in [0.01, 10000] Hz"),
    ({"topic_whitelist": ["("]}, "parameter 'topic_whitelist': '(' is not a valid regular expression"),
    ({"message_backlog_size": 0}, "parameter 'message_backlog_size' must be in [1, 4096] messages"),
    ({"video.codec": "jpeg"}, "parameter 'video.codec': 'jpeg' is a still codec"),
    ({"video.codec": "nocodec"}, "parameter 'video.codec': 'nocodec' is neither"),
    ({"video.quality": 99}, "parameter 'video.quality' (CRF) must be in [0, 51]"),
    ({"video.max_rate": -1.0}, "parameter 'video.max_rate' must be 0 (every frame) or in [0.01, 1000] Hz"),
])
def test_bad_parameters_are_load_errors(rig, parameters: dict[str, Any], message: str) -> None:
    response = rig[1].load("components::FoxgloveBridge", name="bad_bridge", parameters={"port": 0, **parameters})
    assert not response.success and message in response.error_message, response.error_message


def test_binds_loopback_by_default_and_refuses_a_port_in_use(rig) -> None:
    port = free_port()
    unique_id, url = load_bridge(rig, port=port)
    try:
        assert url == f"ws://127.0.0.1:{port}"
        response = rig[1].load("components::FoxgloveBridge", name="second_bridge", parameters={"port": port})
        assert not response.success and f"cannot listen on 127.0.0.1:{port}" in response.error_message
    finally:
        assert rig[1].unload(unique_id).success


# --- the channel queue ----------------------------------------------------------------------------------------
def test_channel_queue_keeps_the_newest_and_counts_what_it_drops() -> None:
    woken: list[int] = []
    queue = ChannelQueue("/t", 3, 0.0, lambda: woken.append(1))
    for n in range(5):
        queue.offer(bytes([n]))
    assert (queue.received, queue.dropped, len(woken)) == (5, 2, 5)
    assert [queue.take()[0] for _ in range(3)] == [b"\x02", b"\x03", b"\x04"] and queue.take() is None


def test_channel_queue_bounds_bytes_and_rate() -> None:
    queue = ChannelQueue("/t", 100, 0.0, lambda: None)
    frame = bytes(MAX_QUEUED_BYTES // 3 + 1)
    for _ in range(4):
        queue.offer(frame)
    assert len(queue) == 2 and queue.dropped == 2
    limited = ChannelQueue("/t", 100, 1.0, lambda: None)
    for _ in range(10):
        limited.offer(b"x")
    assert (len(limited), limited.throttled) == (1, 9)


def test_service_definitions_split_the_srv_file() -> None:
    request, response = service_definitions("std_srvs/srv/SetBool")
    assert request.startswith("bool data") and "---" not in request
    assert response.startswith("bool success") and "string message" in response
    request, _ = service_definitions("rcl_interfaces/srv/SetParameters")
    assert "MSG: rcl_interfaces/Parameter\n" in request and "MSG: rcl_interfaces/ParameterValue\n" in request
    with pytest.raises(ValueError, match="not a service type name"):
        service_definitions("std_msgs/msg/String")
