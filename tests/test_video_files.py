"""Compressed recording that tells the truth: every file of a video topic begins decodable, no frame is lost at a
start, split or resume, and the bag accounts for the frames its encoder lost (issue 35, items 1 to 4).

In-process: a container's manager in the test process with cameras (or the test's own publisher, where the test
must decide how fast frames come), ImageEncoders and recorders. Each file is decoded by Debian's ``ffmpeg``
program on its own: it must give one picture per recorded message, from the file's first message on.
"""
from __future__ import annotations

import os
import random
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rclpy
import yaml
from foxglove_msgs.msg import CompressedVideo
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.qos import QoSProfile
from rosbag2_interfaces.msg import MessagesLostEvent
from sensor_msgs.msg import Image

from component_container.component_manager import ComponentManager
from component_container.component_node import ComponentNode
from component_container.startup_file import load_request
from components.image_encoder.codecs import VideoCodec, choose
from components.image_encoder.image_encoder import ImageEncoder
from components.sensor_driver import stamp_from_ns
from ffmpeg_tools import ffmpeg
from ipc_testing import in_process_manager, wait_until
from ipc_testing.in_process import probe
from test_image_encoder import picture

IPC = {"use_intra_process_comms": True}
WIDTH, HEIGHT = 320, 240


def load(manager: ComponentManager, plugin: str, name: str, **parameters: Any) -> Any:
    return manager.load(load_request({"package": "components", "plugin": f"components::{plugin}", "name": name,
                                      "parameters": parameters, "extra_arguments": IPC}, 1))


def stamp_ns(stamp: Any) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def video_files(bag: Path, topic: str) -> list[list[Any]]:
    """Per file of the bag (in order), the CompressedVideo messages of ``topic`` it holds, read by the mcap
    library's ROS 2 decoder (each file on its own)."""
    files = []
    for path in sorted(bag.glob("*.mcap"), key=lambda p: int(p.stem.rpartition("_")[2])):
        with open(path, "rb") as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            files.append([ros for _, _, _, ros in reader.iter_decoded_messages(topics=[topic])])
    return files


def decoded_frames(messages: list[Any], size: tuple[int, int] = (WIDTH, HEIGHT)) -> tuple[int, str]:
    """How many pictures ffmpeg decodes from these access units, from the first on, and what it complained of."""
    stream = b"".join(bytes(m.data) for m in messages)
    result = subprocess.run([ffmpeg(), "-v", "error", "-f", "h264", "-i", "pipe:0", "-fps_mode", "passthrough",
                             "-f", "rawvideo", "-pix_fmt", "gray", "pipe:1"], input=stream, capture_output=True,
                            timeout=60)
    return len(result.stdout) // (size[0] * size[1]), result.stderr.decode(errors="replace")


def assert_every_file_decodes_whole(bag: Path, topic: str, size: tuple[int, int] = (WIDTH, HEIGHT)
                                    ) -> list[list[Any]]:
    files = video_files(bag, topic)
    with ThreadPoolExecutor(4) as pool:  # one ffmpeg process per file
        results = list(pool.map(lambda messages: decoded_frames(messages, size), [m for m in files if m]))
    for index, (messages, result) in enumerate(zip([m for m in files if m], results)):
        assert result == (len(messages), ""), f"file {index} of {bag} on {topic}"
    return files


@pytest.fixture()
def manager() -> Any:
    with in_process_manager("video_files_test") as manager:
        yield manager


@pytest.mark.parametrize("runs", [3, pytest.param(20, marks=pytest.mark.sweep)])
def test_a_recorder_loaded_beside_running_encoders_begins_every_file_at_a_keyframe(
        manager: ComponentManager, tmp_path: Path, runs: int) -> None:
    """Two cameras and a standalone H.264 encoder run; recorders are loaded and unloaded beside them, each bag
    split every second: ffmpeg decodes every file whole from its first message (before, the recorder did not know
    the topics were video, and files began with delta frames)."""
    for camera in ("c1", "c2"):
        load(manager, "CameraDriver", camera, width=WIDTH, height=HEIGHT, fps=30.0, content="photo",
             topic=f"/{camera}/image_raw")
    load(manager, "ImageEncoder", "enc", codec="h264", regex="image_raw$", polling_interval=0.1)
    topics = [f"/{camera}/image_raw/video" for camera in ("c1", "c2")]
    for run in range(runs):
        bag = tmp_path / f"run{run}"
        recorder = load(manager, "Recorder", f"rec{run}", **{
            "storage.uri": str(bag), "record.topics": topics, "storage.max_bagfile_duration": 1,
            })
        assert wait_until(lambda: len(recorder.node.stats()["current"]["topics"]) == 2 and all(
            t["written"] >= 40 for t in recorder.node.stats()["current"]["topics"].values()), 30.0)
        final = recorder.node.stop_recording()
        manager.unload(recorder.unique_id)
        assert not any("awaiting_keyframe" in r for r in final["drop_reasons"].values()), final["drop_reasons"]
        for topic in topics:
            files = assert_every_file_decodes_whole(bag, topic)
            assert len([f for f in files if f]) >= 2, "the bag was not split"
            assert sum(map(len, files)) == final["topics"][topic]["written"]


def test_a_window_that_opens_later_begins_each_camera_at_the_keyframe_asked_then(manager: ComponentManager,
                                                                                 tmp_path: Path) -> None:
    """record.start_at in the future (``record start --in``): the recorder subscribed long before, and the first
    frames of the window are keyframes, not delta frames left out as awaiting_keyframe (before: up to a whole
    keyframe interval of frames was lost at every start)."""
    load(manager, "CameraDriver", "later_cam", width=WIDTH, height=HEIGHT, fps=30.0, content="photo",
         topic="/later/image")
    bag = tmp_path / "later"
    recorder = load(manager, "Recorder", "rec_later", **{
        "storage.uri": str(bag), "record.compress": "h264", "record.compress_topics": ["/later/image"],
        "record.topics": ["/later/image"], "record.compress_keyframe_interval": 300,
        "record.start_at": time.time() + 1.0})
    assert wait_until(lambda: (recorder.node.stats()["current"]["topics"].get("/later/image/video") or {}).get(
        "written", 0) >= 10, 20.0)
    final = recorder.node.stop_recording()
    assert not any("awaiting_keyframe" in r for r in final["drop_reasons"].values()), final["drop_reasons"]
    assert_every_file_decodes_whole(bag, "/later/image/video")


def test_a_compress_regex_that_matches_nothing_warns_about_each_raw_image_topic(
        manager: ComponentManager, tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    load(manager, "CameraDriver", "raw_cam", width=64, height=48, fps=10.0, topic="/rawcam/image")
    recorder = load(manager, "Recorder", "rec_raw", **{
        "storage.uri": str(tmp_path / "raw"), "record.compress": "jpeg", "record.compress_regex": "/nothing.*",
        "record.topics": ["/rawcam/image"]})
    assert wait_until(lambda: "/rawcam/image" in recorder.node._topics, 20.0)
    recorder.node.stop_recording()
    assert "does not encode /rawcam/image" in capfd.readouterr().err


class Frames(ComponentNode):
    """Publishes the test's pictures as rgb8 Images on several topics in-process, as fast as asked."""

    def __init__(self, manager: ComponentManager, topics: list[str],
                 sizes: dict[str, tuple[int, int]] | None = None) -> None:
        """``sizes``: per topic (width, height), the test's size if not named."""
        super().__init__("video_files_frames", intra_process_manager=manager.intra_process_manager,
                         context=manager.context)
        self.outputs = {topic: self.create_publisher(Image, topic, QoSProfile(depth=10)) for topic in topics}
        self.sizes = {topic: (sizes or {}).get(topic, (WIDTH, HEIGHT)) for topic in topics}
        self.pictures = {size: [np.resize(picture(index), (size[1], size[0], 3)).tobytes() for index in range(20)]
                         for size in set(self.sizes.values())}
        self.sent = 0

    def send(self, topics: list[str] | None = None) -> None:
        """One picture on every topic (or those named), each stamped with the send count (unique per topic)."""
        for topic in topics or list(self.outputs):
            width, height = self.sizes[topic]
            msg = Image(height=height, width=width, encoding="rgb8", step=width * 3)
            msg.header.stamp = stamp_from_ns(1_000_000_000 + self.sent)
            msg.data = self.pictures[(width, height)][self.sent % 20]
            self.outputs[topic].publish(msg)
        self.sent += 1


def test_a_split_keeps_the_frame_another_camera_had_in_hand(manager: ComponentManager, tmp_path: Path) -> None:
    """A split is asked for while a 720p camera's frame is being encoded, and a small camera's keyframe comes
    first: the big camera's frame (a delta frame) still goes to the old file, and each file decodes whole.
    Before, the small camera's keyframe closed the file and the big camera's frame was dropped as
    awaiting_keyframe."""
    small, big = "/hand/small", "/hand/big"
    sizes = {small: (64, 48), big: (1280, 720)}
    bag = tmp_path / "hand"
    recorder = load(manager, "Recorder", "rec_hand", **{
        "storage.uri": str(bag), "record.compress": "h264", "record.compress_topics": [small, big],
        "record.compress_preset": "slow", "record.topics": [small, big]})
    assert wait_until(lambda: all(f"{t}/video" in recorder.node._topics for t in (small, big)), 20.0)
    frames = Frames(manager, [small, big], sizes)
    encoder = next(c.node for c in manager.components() if isinstance(c.node, ImageEncoder))

    def settle() -> None:
        assert wait_until(lambda: all(s["waiting"] == 0 for s in encoder.stats()["topics"].values()), 20.0)

    for _ in range(4):
        for _ in range(3):
            frames.send()
            settle()
        frames.send([big])  # in the encoder's hands ...
        assert recorder.node._session.split()  # ... when the split is asked for
        frames.send([small])
        settle()
    final = recorder.node.stop_recording()
    assert final["drop_reasons"] == {}, final["drop_reasons"]
    for topic in (small, big):
        files = assert_every_file_decodes_whole(bag, f"{topic}/video", sizes[topic])
        assert len([f for f in files if f]) == 5, (topic, [[stamp_ns(m.timestamp) for m in f] for f in files])
        stamps = [stamp_ns(m.timestamp) for messages in files for m in messages]
        assert len(stamps) == len(set(stamps)) == final["topics"][f"{topic}/video"]["written"]


class Arrivals(ComponentNode):
    """Keeps the stamp of every raw frame of ``topics`` it gets in-process, with the monotonic time it came."""

    def __init__(self, manager: ComponentManager, topics: list[str]) -> None:
        super().__init__("video_files_arrivals", intra_process_manager=manager.intra_process_manager,
                         context=manager.context)
        self.stamps: dict[str, list[tuple[int, float]]] = {topic: [] for topic in topics}
        for topic in topics:
            self.create_subscription(Image, topic, lambda m, t=topic: self.stamps[t].append(
                (stamp_ns(m.header.stamp), time.monotonic())), QoSProfile(depth=100), intra_process_inline=True)


@pytest.mark.parametrize("size, splits", [((WIDTH, HEIGHT), 10),
                                          pytest.param((640, 480), 20, marks=pytest.mark.sweep)])
def test_four_cameras_through_splits_and_a_pause_keep_every_frame_once(
        manager: ComponentManager, tmp_path: Path, size: tuple[int, int], splits: int) -> None:
    """record.compress h264 of four free-running cameras, split 10 times (20 at 640x480 in the sweep) and paused
    once: every frame is in
    exactly one file, each file decodes whole from its first message, nothing is awaiting_keyframe, and the
    frames not recorded are those published while paused (or counted as the encoder's losses). Before, each
    split dropped the delta frames of every camera whose keyframe came after the one that closed the file."""
    cameras = [f"/four/cam{i}" for i in range(4)]
    bag = tmp_path / "four"
    recorder = load(manager, "Recorder", "rec_four", **{
        "storage.uri": str(bag), "record.compress": "h264", "record.compress_topics": cameras,
        "record.topics": cameras})
    outputs = [f"{camera}/video" for camera in cameras]
    assert wait_until(lambda: all(o in recorder.node._topics for o in outputs), 20.0)
    arrivals = Arrivals(manager, cameras)
    drivers = [load(manager, "CameraDriver", f"four{i}", width=size[0], height=size[1], fps=30.0, content="photo",
                    topic=camera) for i, camera in enumerate(cameras)]
    session = recorder.node._session
    for split in range(splits):
        time.sleep(0.12)
        assert session.split()
        if split == splits // 2:
            recorder.node._set_paused(True)
            paused_from = time.monotonic()
            time.sleep(0.3)
            paused_until = time.monotonic()
            recorder.node._set_paused(False)
    for driver in drivers:
        manager.unload(driver.unique_id)
    encoder = next(c.node for c in manager.components() if isinstance(c.node, ImageEncoder))
    assert wait_until(lambda: all(s["waiting"] == 0 for s in encoder.stats()["topics"].values()), 20.0)
    final = recorder.node.stop_recording()
    assert {t: r for t, r in final["drop_reasons"].items() if "awaiting_keyframe" in r} == {}, final["drop_reasons"]
    for camera, output in zip(cameras, outputs):
        files = assert_every_file_decodes_whole(bag, output, size)
        assert len([f for f in files if f]) >= splits // 2  # splits asked for before the next frame are one
        stamps = [stamp_ns(m.timestamp) for messages in files for m in messages]
        assert len(stamps) == len(set(stamps)), "a frame in two files"
        # a frame in hand at the pause or the resume is published just after it: one frame interval of slack
        missing = [(s, t) for s, t in arrivals.stamps[camera] if s not in set(stamps)
                   and not paused_from - 0.05 <= t <= paused_until + 0.05]
        assert len(missing) <= final["topics"][output]["dropped"], (missing, final["drop_reasons"])


def test_an_overloaded_encoder_is_in_the_bags_accounting(manager: ComponentManager, tmp_path: Path) -> None:
    """Frames sent faster than the encoder takes them: the frames it skipped are the topic's drops in
    ~/get_stats, the close summary and the bag's metadata.yaml (which `bag info` prints), so that written plus
    counted losses equal the frames sent, per camera. A rate limit on one camera thins the encoder's input, and
    every access unit recorded still decodes (before, the recorder left out access units after the encoder)."""
    cameras = ["/over/cam0", "/over/cam1"]
    bag = tmp_path / "over"
    recorder = load(manager, "Recorder", "rec_over", **{
        "storage.uri": str(bag), "record.compress": "h264", "record.compress_topics": cameras,
        "record.compress_preset": "slow", "record.topics": cameras,
        "record.max_rates": ["/over/cam1/video:10"]})
    outputs = [f"{camera}/video" for camera in cameras]
    assert wait_until(lambda: all(o in recorder.node._topics for o in outputs), 20.0)
    losses = probe(manager, MessagesLostEvent, "/events/messages_lost")
    frames = Frames(manager, cameras)
    for _ in range(60):  # a burst: the encoder's mailbox of two overflows
        frames.send()
    for _ in range(30):  # then 100 Hz, above the limit of 10 Hz
        frames.send()
        time.sleep(0.01)
    encoder = next(c.node for c in manager.components() if isinstance(c.node, ImageEncoder))
    assert wait_until(lambda: all(s["waiting"] == 0 for s in encoder.stats()["topics"].values()), 30.0)
    assert wait_until(lambda: all(
        recorder.node.stats()["current"]["topics"][o]["received"]
        == sum(encoder.stats()["topics"][c][k] for k in ("published", "skipped", "rejected", "stopped"))
        + recorder.node.stats()["current"]["topics"][o]["rate_limited"] for o, c in zip(outputs, cameras)), 20.0)
    final = recorder.node.stop_recording()
    custom = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["custom_data"]
    for output in outputs:
        counts = final["topics"][output]
        assert counts["received"] == frames.sent, counts
        assert counts["written"] + counts["dropped"] + counts["rate_limited"] == frames.sent, counts
        account = {name: int(n) for name, n in (pair.split("=") for pair in custom[f"recorder.frames.{output}"].split())}
        assert account == {"received": frames.sent, "written": counts["written"],
                           **final["drop_reasons"].get(output, {}), "rate_limited": counts["rate_limited"]}
        assert_every_file_decodes_whole(bag, output)
    assert final["drop_reasons"]["/over/cam0/video"]["encoder_behind"] > 0, final["drop_reasons"]
    reported = sum(stat.messages_lost_in_transport for event in losses.messages for stat in event.messages_lost_statistics
                   if stat.topic_name == "/over/cam0/video")
    assert reported == final["drop_reasons"]["/over/cam0/video"]["encoder_behind"]  # events/messages_lost
    assert final["topics"]["/over/cam1/video"]["rate_limited"] > 0
    assert final["topics"]["/over/cam0/video"]["rate_limited"] == 0
    info = subprocess.run([sys.executable, "-m", "ipc_component.cli", "bag", "info", str(bag)], capture_output=True,
                          text=True, timeout=30)
    assert f"Frames: {outputs[0]} | Received: {frames.sent}" in info.stdout, info.stdout


@pytest.mark.parametrize("cycles", [15, pytest.param(400, marks=pytest.mark.sweep)])
def test_pauses_of_any_length_leave_nothing_awaiting_a_keyframe(manager: ComponentManager, tmp_path: Path,
                                                                cycles: int) -> None:
    """Two cameras recorded compressed, paused and resumed ``cycles`` times for seeded random moments of 0 to 40
    ms: each resume begins every camera at a keyframe, nothing is left out as awaiting_keyframe. Before, a delta
    frame the encoder published between the resume and its keyframe request began a camera and was dropped."""
    seed = int(os.environ.get("IPC_PAUSE_SEED") or 7)
    print(f"IPC_PAUSE_SEED={seed}")
    generator = random.Random(seed)
    cameras = ["/pause/cam0", "/pause/cam1"]
    bag = tmp_path / "pauses"
    recorder = load(manager, "Recorder", "rec_pause", **{
        "storage.uri": str(bag), "record.compress": "h264", "record.compress_topics": cameras,
        "record.topics": cameras})
    assert wait_until(lambda: all(f"{c}/video" in recorder.node._topics for c in cameras), 20.0)
    for i, camera in enumerate(cameras):
        load(manager, "CameraDriver", f"pause{i}", width=WIDTH, height=HEIGHT, fps=60.0, topic=camera)
    for _ in range(cycles):
        time.sleep(generator.uniform(0.0, 0.04))
        recorder.node._set_paused(True)
        time.sleep(generator.uniform(0.0, 0.04))
        recorder.node._set_paused(False)
    time.sleep(0.2)
    final = recorder.node.stop_recording()
    assert {t: r for t, r in final["drop_reasons"].items() if "awaiting_keyframe" in r} == {}, final["drop_reasons"]
    for camera in cameras:
        assert_every_file_decodes_whole(bag, f"{camera}/video")


@pytest.mark.parametrize("intra_process", [True, False])
def test_video_of_another_publisher_begins_every_file_at_its_own_keyframes(manager: ComponentManager,
                                                                           tmp_path: Path, intra_process: bool) -> None:
    """A CompressedVideo topic that no encoder of the container publishes (a plain rclpy publisher: over DDS, as
    serialized bytes), joined in the middle of a keyframe interval and split twice, by a recorder with and without
    intra-process comms: FFmpeg's parser finds its keyframes, so the bag begins at the first one (the delta frames
    before it dropped as awaiting_keyframe), each split file begins at one, and every other access unit is
    recorded exactly once. Before, it was recorded as it came: its first file began with delta frames that ffmpeg
    cannot decode, and so could every split file."""
    topic, interval, first = "/foreign/video", 10, 3
    codec = VideoCodec(choose("h264", "", -1, 0, interval), WIDTH, HEIGHT)
    units = [(keyframe, data) for index in range(60)
             for _, keyframe, data in codec.encode(picture(index), "rgb8", False)]
    assert [k for k, _ in units[:interval + 1]] == [True] + [False] * (interval - 1) + [True]
    bag = tmp_path / "foreign"
    recorder = manager.load(load_request({
        "package": "components", "plugin": "components::Recorder", "name": "rec_foreign",
        "parameters": {"storage.uri": str(bag), "record.topics": [topic]},
        "extra_arguments": IPC if intra_process else {}}, 1))
    node = rclpy.create_node("foreign_video", context=manager.context)  # not the container's: DDS only
    try:
        publisher = node.create_publisher(CompressedVideo, topic, QoSProfile(depth=100))
        assert wait_until(lambda: topic in recorder.node._topics and publisher.get_subscription_count() >= 1, 20.0)

        def received() -> int:
            return recorder.node.stats()["current"]["topics"].get(topic, {}).get("received", 0)

        for sent, (_, data) in enumerate(units[first:], start=1):
            message = CompressedVideo(frame_id="foreign", format="h264", data=data)
            message.timestamp = stamp_from_ns(1_000_000_000 + first + sent)
            publisher.publish(message)
            assert wait_until(lambda: received() == sent, 10.0), (sent, received())
            if first + sent in (25, 45):  # mid-interval: the split waits for the next keyframe
                assert recorder.node._session.split()
        final = recorder.node.stop_recording()
    finally:
        node.destroy_node()
    assert final["drop_reasons"] == {topic: {"awaiting_keyframe": interval - first}}, final["drop_reasons"]
    files = assert_every_file_decodes_whole(bag, topic)
    assert [len(messages) for messages in files] == [20, 20, 10], [len(messages) for messages in files]
    stamps = [stamp_ns(m.timestamp) - 1_000_000_000 for messages in files for m in messages]
    assert stamps == list(range(interval + 1, len(units) + 1))  # each unit once, in order, from the keyframe on
