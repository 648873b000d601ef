"""Compressed bags on the way back: the player decoding to ``sensor_msgs/Image``, and ``bag export``.

The bags are written here from the image encoder's own codecs (components/image_encoder/codecs.py) over photographic
frames (components/photo_content.py): a CompressedVideo topic (H.264) and a CompressedImage topic (JPEG), with
BagWriter, which is what the recorder writes for them without the cost of a recording. The player runs in an
in-process manager beside inline probes (they see every message without an executor); ``bag play --decode`` and
``bag export`` run as the commands users run, checked with an rclpy subscriber over Fast DDS and with Debian's
``ffmpeg`` / ``ffprobe`` programs.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import pytest
from foxglove_msgs.msg import CompressedVideo
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CompressedImage, Image

from baglib.format.metadata import TopicInfo, qos_profile_dict
from baglib.read.reader import BagMessage, BagReader
from baglib.read.timeline import Timeline
from baglib.write.writer import BagWriter
from component_container.component_manager import ComponentConstructionError, ComponentManager
from component_container.startup_file import load_request
from components.image_encoder import codecs
from components.image_encoder.frame_times import frame_times
from components.player.decode_worker import NICE, Job, StreamWorker
from components.player.decoded_topics import DecodedStream, Decoding, decoded_name
from components.player.playback import HEAD_START_NS
from components.player.read_ahead import ReadAhead
from components.photo_content import PhotoContent
from components.sensor_driver import stamp_from_ns
from ipc_testing import in_process_manager, wait_until
from ipc_testing.in_process import InlineProbe, probe
from ipc_testing.playback import play

WIDTH, HEIGHT = 320, 240
FRAMES = 12
KEYFRAME_INTERVAL = 5
PERIOD_NS = 20_000_000
T0 = 1_700_000_000_000_000_000
VIDEO, STILLS = "/cam/image/video", "/cam2/image/compressed"
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
CLI = str(Path(sys.executable).with_name("ipc-component"))
#: Decoded against the raw frames (the codecs' defaults gave 38-41 dB here): the issue's target for H.264.
MIN_PSNR_DB = 36.0


def program(name: str) -> str:
    """Debian's ffmpeg / ffprobe; the tests fail (never skip) without it: `make test` installs the package."""
    path = shutil.which(name)
    if path is None:
        pytest.fail(f"the {name} program is missing: `apt-get install -y ffmpeg` (`make test` does this)")
    return path


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def camera_topics(camera: int) -> tuple[str, str]:
    """The video and the JPEG topic of camera pair ``camera`` (0: VIDEO and STILLS)."""
    return (VIDEO, STILLS) if camera == 0 else (f"/cam{2 * camera + 1}/image/video",
                                                f"/cam{2 * camera + 2}/image/compressed")


def stamp_ns(index: int, camera: int = 0) -> int:
    """Frame ``index`` of camera pair ``camera``: the pairs 1 us apart, so that no stream has another's stamps."""
    return T0 + index * PERIOD_NS + camera * 1000


class CompressedBag:
    """A bag of FRAMES photographic frames as video (VIDEO, H.264 unless told) and JPEG (STILLS), and what
    went into it; ``offsets_ns``: the frames' stamps after T0 (default: every PERIOD_NS), and as many frames; with
    ``cameras`` > 1 the same pictures also on the topics of more pairs (camera_topics), each pair with stamps of
    its own (1 us apart) and frame_id ``camera<pair>``."""

    def __init__(self, path: Path, raw_topic: str = "", codec: str = "h264", cameras: int = 1,
                 offsets_ns: Sequence[int] = tuple(index * PERIOD_NS for index in range(FRAMES))) -> None:
        self.path = path
        self.frames: list[np.ndarray] = []
        self.video: list[bytes] = []
        self.keyframes: list[bool] = []
        self.jpegs: list[bytes] = []
        self.topics = [topic for camera in range(cameras) for topic in camera_topics(camera)]
        content = PhotoContent(WIDTH, HEIGHT, "rgb8")
        video = codecs.VideoCodec(codecs.choose(codec, "", -1, 0, KEYFRAME_INTERVAL), WIDTH, HEIGHT)
        jpeg = codecs.StillCodec(codecs.choose("jpeg", "", -1, 0, KEYFRAME_INTERVAL), 0)
        with BagWriter(path) as writer:
            for topic in self.topics:
                writer.add_topic(TopicInfo(topic, "foxglove_msgs/msg/CompressedVideo" if topic.endswith("/video")
                                           else "sensor_msgs/msg/CompressedImage",
                                           offered_qos_profiles=[qos_profile_dict(RELIABLE)]))
            if raw_topic:
                writer.add_topic(TopicInfo(raw_topic, "sensor_msgs/msg/Image"))
            for index, offset in enumerate(offsets_ns):
                buffer = bytearray(WIDTH * HEIGHT * 3)
                content.fill(index, memoryview(buffer))
                pixels = np.frombuffer(bytes(buffer), np.uint8).reshape(HEIGHT, WIDTH, 3)
                image = Image(height=HEIGHT, width=WIDTH, encoding="rgb8", step=WIDTH * 3)
                image.data = pixels.tobytes()
                self.frames.append(pixels)
                [(_, keyframe, data)] = video.encode(pixels, "rgb8", False)
                self.video.append(data)
                self.keyframes.append(keyframe)
                self.jpegs.append(jpeg.encode(image))
                for camera in range(cameras):
                    t = T0 + offset + camera * 1000
                    image.header.stamp, image.header.frame_id = stamp_from_ns(t), f"camera{camera or ''}"
                    frame = CompressedVideo(timestamp=image.header.stamp, frame_id=image.header.frame_id,
                                            format=codec)
                    frame.data = data
                    still = CompressedImage(header=image.header, format=jpeg.format_of("rgb8"))
                    still.data = self.jpegs[-1]
                    video_topic, still_topic = camera_topics(camera)
                    writer.write(video_topic, serialize_message(frame), t, t)
                    writer.write(still_topic, serialize_message(still), t, t)
        assert self.keyframes[0] and sum(self.keyframes) >= -(-len(offsets_ns) // KEYFRAME_INTERVAL)


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> CompressedBag:
    return CompressedBag(tmp_path_factory.mktemp("decoded") / "bag")


@pytest.fixture()
def manager() -> Iterator[ComponentManager]:
    with in_process_manager("decoded_playback_test") as manager:
        yield manager


def image_probe(manager: ComponentManager, topic: str) -> InlineProbe:
    """Every Image of ``topic`` the manager's components publish (reliable, as the player's publishers)."""
    return probe(manager, Image, topic, RELIABLE)


def load_player(manager: ComponentManager, uri: Path, **parameters: Any) -> Any:
    return manager.load(load_request({
        "package": "components", "plugin": "components::Player", "name": "player",
        "parameters": {"storage.uri": str(uri), **parameters},
        "extra_arguments": {"use_intra_process_comms": True}}, 1)).node


def pixels_of(image: Image) -> np.ndarray:
    return np.frombuffer(bytes(image.data), np.uint8).reshape(image.height, image.width, 3)


def test_a_compressed_bag_plays_as_images_of_the_original_size_encoding_and_stamps(
        manager: ComponentManager, bag: CompressedBag) -> None:
    video, stills = image_probe(manager, "/cam/image"), image_probe(manager, "/cam2/image")
    player = load_player(manager, bag.path, **{"play.decode": True})
    assert wait_until(lambda: len(video.messages) == FRAMES and len(stills.messages) == FRAMES, 30.0), \
        (len(video.messages), len(stills.messages))
    assert player._playback.wait_finished(30.0)
    stamps = [stamp_from_ns(T0 + index * PERIOD_NS) for index in range(FRAMES)]
    for probe in (video, stills):
        assert [m.header.stamp for m in probe.messages] == stamps  # one per recorded frame, in order
        assert {(m.width, m.height, m.encoding, m.step, m.header.frame_id) for m in probe.messages} == {
            (WIDTH, HEIGHT, "rgb8", WIDTH * 3, "camera")}
        for got, sent in zip(probe.messages, bag.frames):
            assert psnr(pixels_of(got), sent) >= MIN_PSNR_DB
    decoded = player.stats()["decoded"]
    assert decoded == {VIDEO: {"topic": "/cam/image", "decoded": FRAMES, "skipped": 0, "failed": 0},
                       STILLS: {"topic": "/cam2/image", "decoded": FRAMES, "skipped": 0, "failed": 0}}


def test_a_video_stream_starts_at_a_keyframe_and_counts_the_frames_before_it(
        manager: ComponentManager, bag: CompressedBag) -> None:
    video = image_probe(manager, "/cam/image")
    start = 2  # two frames into the first group of pictures
    player = load_player(manager, bag.path, **{"play.decode_topics": [VIDEO],
                                               "play.start_offset.nsec": start * PERIOD_NS})
    assert player._playback.wait_finished(30.0)
    first = bag.keyframes.index(True, start)
    assert [m.header.stamp for m in video.messages] == [
        stamp_from_ns(T0 + index * PERIOD_NS) for index in range(first, FRAMES)]
    assert player.stats()["decoded"] == {
        VIDEO: {"topic": "/cam/image", "decoded": FRAMES - first, "skipped": first - start, "failed": 0}}


def test_a_frame_that_fails_to_decode_is_counted_and_its_compressed_message_still_plays(
        manager: ComponentManager, bag: CompressedBag, tmp_path: Path) -> None:
    damaged = 3
    with BagWriter(tmp_path / "damaged") as writer:
        writer.add_topic(TopicInfo(STILLS, "sensor_msgs/msg/CompressedImage"))
        for index, data in enumerate(bag.jpegs):
            still = CompressedImage(header=Image().header, format="rgb8; jpeg compressed bgr8")
            still.header.stamp = stamp_from_ns(T0 + index * PERIOD_NS)
            still.data = data if index != damaged else b"\xff\xd8 not a picture"
            writer.write(STILLS, serialize_message(still), T0 + index * PERIOD_NS, T0 + index * PERIOD_NS)
    images = image_probe(manager, "/cam2/image")
    player = load_player(manager, tmp_path / "damaged", **{"play.decode": True})
    assert player._playback.wait_finished(30.0)
    assert len(images.messages) == FRAMES - 1
    assert player.stats()["decoded"][STILLS] == {"topic": "/cam2/image", "decoded": FRAMES - 1, "skipped": 0,
                                                 "failed": 1}
    assert player.stats()["published"][STILLS] == FRAMES


def decode_threads() -> list[str]:
    """The names of the decoding threads alive in this process (decode_worker.py names them ``decode:<topic>``)."""
    return sorted(thread.name for thread in threading.enumerate() if thread.name.startswith("decode:"))


def test_several_streams_decode_side_by_side_each_frame_once_and_in_order(
        manager: ComponentManager, tmp_path: Path) -> None:
    cameras = 2
    bag = CompressedBag(tmp_path / "bag", cameras=cameras)
    outputs = {topic: topic.rpartition("/")[0] for topic in bag.topics}
    probes = {topic: image_probe(manager, output) for topic, output in outputs.items()}
    player = load_player(manager, bag.path, **{"play.decode": True})
    assert player._playback.wait_finished(30.0)
    for camera in range(cameras):
        for topic in camera_topics(camera):
            got = probes[topic].messages
            assert [m.header.stamp for m in got] == [stamp_from_ns(stamp_ns(i, camera)) for i in range(FRAMES)], topic
            assert {m.header.frame_id for m in got} == {f"camera{camera or ''}"}
            for image, sent in zip(got, bag.frames):
                assert psnr(pixels_of(image), sent) >= MIN_PSNR_DB
    assert player.stats()["decoded"] == {
        topic: {"topic": output, "decoded": FRAMES, "skipped": 0, "failed": 0} for topic, output in outputs.items()}
    assert wait_until(lambda: decode_threads() == [], 10.0), decode_threads()  # each ends with its pass


def test_each_loop_decodes_the_bag_again_from_its_first_keyframe(manager: ComponentManager, bag: CompressedBag
                                                                 ) -> None:
    video = image_probe(manager, "/cam/image")
    player = load_player(manager, bag.path, **{"play.decode_topics": [VIDEO], "play.loop": True})
    assert wait_until(lambda: len(video.messages) >= 2 * FRAMES, 30.0), len(video.messages)
    player.stop()
    stamps = [stamp_from_ns(stamp_ns(index)) for index in range(FRAMES)]
    assert [m.header.stamp for m in video.messages[:2 * FRAMES]] == stamps + stamps
    assert player.stats()["decoded"][VIDEO]["failed"] == player.stats()["decoded"][VIDEO]["skipped"] == 0


def test_a_pass_waits_for_the_pictures_of_its_head_start_before_its_clock_starts(
        manager: ComponentManager, bag: CompressedBag) -> None:
    node = image_probe(manager, "/unused")
    logged: list[str] = []
    decoding = Decoding([DecodedStream(node, topic, decoded_name(topic), topic == VIDEO, RELIABLE, msg_class,
                                       logged.append) for topic, msg_class in ((VIDEO, CompressedVideo),
                                                                               (STILLS, CompressedImage))])
    timeline = Timeline([bag.path])
    errors: list[BaseException] = []
    read_ahead = ReadAhead(timeline, [VIDEO, STILLS], 1000, 256 << 20, errors.append, decoding)
    try:
        read_ahead.restart(timeline.starting_time_ns)  # what a run does before playback's head start
        assert read_ahead.wait_decoded(HEAD_START_NS, 30.0)
        # The whole bag is within the head start: when the wait ends, every message is queued and decoded.
        assert FRAMES * PERIOD_NS < HEAD_START_NS
        queued = read_ahead.head(4 * FRAMES)
        assert len(queued) == 2 * FRAMES and all(item.decoding.wait_done(0.0) for item in queued)
        for item in queued:
            item.take_decoded()
        assert [item.decoded.header.stamp for item in queued if item.message.connection.topic == VIDEO] == [
            stamp_from_ns(stamp_ns(index)) for index in range(FRAMES)]
    finally:
        read_ahead.close()
        timeline.close()
    assert errors == [] and logged == [] and decode_threads() == []


def test_a_stream_whose_frames_all_fail_does_not_hold_up_the_others(
        manager: ComponentManager, bag: CompressedBag, tmp_path: Path) -> None:
    broken_still, broken_video = "/broken/image/compressed", "/broken_video/image/video"
    with BagWriter(tmp_path / "mixed") as writer:
        for topic, msgtype in ((VIDEO, "foxglove_msgs/msg/CompressedVideo"),
                               (STILLS, "sensor_msgs/msg/CompressedImage"),
                               (broken_still, "sensor_msgs/msg/CompressedImage"),
                               (broken_video, "foxglove_msgs/msg/CompressedVideo")):
            writer.add_topic(TopicInfo(topic, msgtype))
        for index in range(FRAMES):
            t = stamp_ns(index)
            stamp = stamp_from_ns(t)
            good_video = CompressedVideo(timestamp=stamp, frame_id="camera", format="h264")
            good_video.data = bag.video[index]
            good_still = CompressedImage(format="rgb8; jpeg compressed bgr8")
            good_still.header.stamp = stamp
            good_still.data = bag.jpegs[index]
            bad_still = CompressedImage(format="jpeg")
            bad_still.data = b"\xff\xd8 not a picture"
            bad_video = CompressedVideo(timestamp=stamp, format="vp9")  # a format the player does not decode
            bad_video.data = bag.video[index]
            for topic, message in ((broken_still, bad_still), (VIDEO, good_video), (broken_video, bad_video),
                                   (STILLS, good_still)):
                writer.write(topic, serialize_message(message), t, t)
    video, stills = image_probe(manager, "/cam/image"), image_probe(manager, "/cam2/image")
    player = load_player(manager, tmp_path / "mixed", **{"play.decode": True})
    assert player._playback.wait_finished(30.0)
    stamps = [stamp_from_ns(stamp_ns(index)) for index in range(FRAMES)]
    assert [m.header.stamp for m in video.messages] == stamps
    assert [m.header.stamp for m in stills.messages] == stamps
    stats = player.stats()
    assert stats["decoded"] == {
        VIDEO: {"topic": "/cam/image", "decoded": FRAMES, "skipped": 0, "failed": 0},
        STILLS: {"topic": "/cam2/image", "decoded": FRAMES, "skipped": 0, "failed": 0},
        broken_still: {"topic": "/broken/image", "decoded": 0, "skipped": 0, "failed": FRAMES},
        broken_video: {"topic": "/broken_video/image", "decoded": 0, "skipped": 0, "failed": FRAMES}}
    assert {topic: stats["published"][topic] for topic in (VIDEO, STILLS, broken_still, broken_video)} == {
        VIDEO: FRAMES, STILLS: FRAMES, broken_still: FRAMES, broken_video: FRAMES}


def test_a_stream_decodes_ahead_of_playback_with_a_bounded_number_of_frames_in_flight(
        bag: CompressedBag) -> None:
    depth = 3
    with BagReader(bag.path) as reader:
        messages = [message._replace(data=bytes(message.data)) for message in reader.messages([VIDEO])]
    gate = threading.Semaphore(0)
    decoded: list[BagMessage] = []

    def decode(job: Job) -> tuple[Any, Any]:  # a decoder held at the gate, one message per release
        gate.acquire()
        decoded.append(job.message)
        return job.message, None

    worker = StreamWorker("decode:bounded", decode, depth)
    jobs: list[Job] = []

    def read() -> None:  # the read-ahead thread's part
        for message in messages:
            job = Job(message, 0, False)
            worker.submit(job)
            jobs.append(job)

    reader_thread = threading.Thread(target=read)
    reader_thread.start()
    try:
        assert wait_until(lambda: worker.in_flight == depth, 10.0)  # ahead: the reader did not wait for the first
        for released in range(len(messages)):
            assert worker.in_flight <= depth and len(jobs) <= depth + released  # then it waits for a free place
            gate.release()
            assert wait_until(lambda: len(decoded) == released + 1, 10.0)
        reader_thread.join(10.0)
        assert decoded == messages and [job.wait()[0] for job in jobs] == messages  # in order, each once
    finally:
        gate.release(len(messages))
        worker.close()
    assert not reader_thread.is_alive() and decode_threads() == []


@pytest.mark.skipif(sys.platform != "linux", reason="a nice value per thread is Linux's")
def test_a_stream_decodes_at_a_lower_priority_than_the_reader_and_so_do_the_threads_its_codec_starts(
        bag: CompressedBag) -> None:
    seen: list[int] = []

    def priority() -> None:
        seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))

    def decode(job: Job) -> tuple[Any, Any]:  # its own priority, and that of a thread it starts (as FFmpeg does)
        priority()
        codec_thread = threading.Thread(target=priority)
        codec_thread.start()
        codec_thread.join()
        return job.message, None

    with BagReader(bag.path) as reader:
        message = next(iter(reader.messages([VIDEO])))
    worker = StreamWorker("decode:priority", decode, 1)
    reader_priority = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    try:
        job = Job(message._replace(data=bytes(message.data)), 0, True)
        worker.submit(job)
        job.wait()
    finally:
        worker.close()
    assert seen == [min(reader_priority + NICE, 19)] * 2
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == reader_priority  # the reader's is unchanged


def test_a_decoding_thread_per_stream_that_stop_and_unload_end(manager: ComponentManager, tmp_path: Path) -> None:
    bag = CompressedBag(tmp_path / "bag", cameras=2)
    streams = sorted(f"decode:{topic}" for topic in bag.topics)
    images = image_probe(manager, "/cam/image")
    # Paused with a read-ahead of one message per stream: every stream has a message handed to its thread, and the
    # pass cannot end, so the threads wait for more.
    loaded = manager.load(load_request({
        "package": "components", "plugin": "components::Player", "name": "player",
        "parameters": {"storage.uri": str(bag.path), "play.decode": True, "play.start_paused": True,
                       "play.read_ahead_queue_size": len(streams)},
        "extra_arguments": {"use_intra_process_comms": True}}, 1))
    player = loaded.node
    assert wait_until(lambda: decode_threads() == streams, 10.0), decode_threads()
    player.stop()
    assert wait_until(lambda: decode_threads() == [], 10.0), decode_threads()
    player.resume()
    assert player.play()
    assert wait_until(lambda: len(images.messages) >= 2, 10.0)  # decoding again, on new threads
    assert manager.unload(loaded.unique_id).found
    assert decode_threads() == [] and not [t.name for t in threading.enumerate() if t.name.startswith("player-")]


@pytest.mark.parametrize(("parameters", "names"), [
    ({"play.decode_topics": ["/cam/raw"]}, ["play.decode_topics", "/cam/raw", "sensor_msgs/msg/Image"]),
    ({"play.decode_topics": ["/nowhere"]}, ["play.decode_topics", "/nowhere", "not a played topic"]),
    ({"play.decode": True}, ["play.decode", VIDEO, "'/cam/image'"]),
])
def test_a_bad_choice_is_a_load_error_naming_it_and_the_container_keeps_running(
        manager: ComponentManager, tmp_path: Path, parameters: dict[str, Any], names: list[str]) -> None:
    clashing = CompressedBag(tmp_path / "bag", raw_topic="/cam/image")
    with BagWriter(tmp_path / "raw") as writer:
        writer.add_topic(TopicInfo("/cam/raw", "sensor_msgs/msg/Image"))
        writer.write("/cam/raw", serialize_message(Image()), T0, T0)
    uri = tmp_path / "raw" if "/cam/raw" in names else clashing.path
    with pytest.raises(ComponentConstructionError) as error:
        load_player(manager, uri, **parameters)
    for name in names:
        assert name in str(error.value)
    assert load_player(manager, clashing.path, **{"play.decode_topics": [STILLS]}) is not None


def test_bag_play_decode_before_the_bag_plays_it_and_its_errors_name_the_options(tmp_path: Path) -> None:
    """``bag play --decode BAG`` (the bag after the option) takes BAG; the player's refusal (a decoded topic would
    clash with a played one) names the options the user typed, not the player's parameters."""
    clashing = CompressedBag(tmp_path / "bag", raw_topic="/cam/image")
    result = subprocess.run([CLI, "bag", "play", "--no-progress", "--decode", str(clashing.path)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 1
    assert f"Cannot play {clashing.path}: --decode: '{VIDEO}' would be decoded to '/cam/image', which '/cam/image' " \
           "is played on too; exclude one of them (--exclude-topics) or choose the topics to decode with --decode\n" \
           in result.stderr, result.stderr


def test_bag_play_decode_delivers_images_over_dds(probe: Node, bag: CompressedBag) -> None:
    got, _ = play(probe, [CLI, "bag", "play", str(bag.path), "--decode", VIDEO, "--wait-for-all-acked", "10000"],
                  "/cam/image", Image, played_topic=VIDEO, qos=RELIABLE)
    assert [m.header.stamp for m in got] == [stamp_from_ns(T0 + index * PERIOD_NS) for index in range(FRAMES)]
    assert {(m.width, m.height, m.encoding) for m in got} == {(WIDTH, HEIGHT, "rgb8")}
    assert min(psnr(pixels_of(m), sent) for m, sent in zip(got, bag.frames)) >= MIN_PSNR_DB


def ffprobe(path: Path, *entries: str) -> Any:
    result = subprocess.run([program("ffprobe"), "-v", "error", "-count_packets", "-show_entries", ",".join(entries),
                             "-of", "json", str(path)], capture_output=True, text=True, timeout=60, check=True)
    return json.loads(result.stdout)


def decoded_by_ffmpeg(data: bytes, demuxer: str) -> bytes:
    """What Debian's ffmpeg decodes ``data`` (read with ``demuxer``) to: raw rgb24 frames."""
    return subprocess.run([program("ffmpeg"), "-v", "error", "-f", demuxer, "-i", "pipe:0", "-fps_mode", "passthrough",
                           "-f", "rawvideo", "-pix_fmt", "rgb24", "pipe:1"], input=data, capture_output=True,
                          timeout=60, check=True).stdout


@pytest.mark.parametrize(("codec", "demuxer", "tag"), [("h264", "h264", "avc1"), ("h265", "hevc", "hev1"),
                                                      ("av1", "obu", "av01")])
def test_bag_export_remuxes_a_video_topic_into_mp4_without_re_encoding(
        tmp_path: Path, codec: str, demuxer: str, tag: str) -> None:
    bag = CompressedBag(tmp_path / "bag", codec=codec)
    out = tmp_path / "video.mp4"
    result = subprocess.run([CLI, "bag", "export", str(bag.path), VIDEO, str(out)], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"Wrote 1 MP4 file ({FRAMES} frames) of {VIDEO} ({codec}) to {out}, as recorded (no " \
                            "re-encoding)\n"
    [stream] = ffprobe(out, "stream=codec_name,codec_tag_string,width,height,nb_read_packets")["streams"]
    assert stream == {"codec_name": {"h265": "hevc"}.get(codec, codec), "codec_tag_string": tag, "width": WIDTH,
                      "height": HEIGHT, "nb_read_packets": str(FRAMES)}
    packets = ffprobe(out, "packet=pts_time,flags")["packets"]
    assert [round(float(p["pts_time"]) * 1e9) for p in packets] == [index * PERIOD_NS for index in range(FRAMES)]
    assert [p["flags"].startswith("K") for p in packets] == bag.keyframes
    # Not re-encoded: ffmpeg decodes the MP4 to exactly the pictures of the recorded stream, bit for bit.
    assert decoded_by_ffmpeg(out.read_bytes(), "mp4") == decoded_by_ffmpeg(b"".join(bag.video), demuxer)


def test_bag_export_of_frames_stamped_in_bursts_is_read_by_ffmpeg_without_warnings(tmp_path: Path) -> None:
    """Stamps as a 30 Hz camera that catches up after stalls gives them: three bursts of frames 1.4 ms apart. The
    MP4 keeps every frame in order, each at least the camera's frame interval after the one before (a burst spreads
    into the stall before it) and otherwise at its stamp, and ffmpeg decodes it with its own timing (``-f null``,
    which times frames at its guess of the frame rate) without a warning."""
    period = 33_333_333
    offsets = [index * period for index in range(45)]
    for burst in (10, 25, 40):  # the frames due at burst - 2 and burst - 1 come late, with the one due at burst
        offsets[burst - 2:burst + 1] = [burst * period - 2_800_000, burst * period - 1_400_000, burst * period]
    bag = CompressedBag(tmp_path / "bag", offsets_ns=offsets)
    out = tmp_path / "video.mp4"
    result = subprocess.run([CLI, "bag", "export", str(bag.path), VIDEO, str(out)], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    read = subprocess.run([program("ffmpeg"), "-hide_banner", "-i", str(out), "-f", "null", "-"], capture_output=True,
                          text=True, timeout=60)
    assert read.returncode == 0 and "non monotonically increasing dts" not in read.stderr, read.stderr
    times = [round(float(p["pts_time"]) * 1e9) for p in ffprobe(out, "packet=pts_time")["packets"]]
    assert len(times) == len(offsets) and all(later - earlier >= period - 1_000_000
                                              for earlier, later in zip(times, times[1:])), times
    assert max(abs(t - offset) for t, offset in zip(times, offsets)) < 2 * period, times
    assert all(abs(t - offset) <= 11_112 for t, offset in zip(times[:8], offsets[:8])), times  # the stamps (90 kHz)
    assert decoded_by_ffmpeg(out.read_bytes(), "mp4") == decoded_by_ffmpeg(b"".join(bag.video), "h264")  # in order


def test_frame_times_keep_regular_and_rate_changing_stamps_and_spread_a_burst_into_the_stall_before_it() -> None:
    ms = 1_000_000
    changing = [index * 66 * ms for index in range(20)] + [(1287 + index * 33) * ms for index in range(40)]
    assert [round(t) for t in frame_times(changing)] == changing  # 15 Hz, then 30 Hz: nothing moves
    # the frames due at 99 and 132 ms come late, 1.4 ms apart, with the one due at 165 ms
    stalled = [0, 33 * ms, 66 * ms, 162_200_000, 163_600_000, 165 * ms] + [(198 + 33 * i) * ms for i in range(40)]
    times = frame_times(stalled)
    assert times[:3] == [0, 33 * ms, 66 * ms] and all(b - a >= 33 * ms - 1 for a, b in zip(times, times[1:]))
    assert 99 * ms < times[3] < 105 * ms and abs(times[-1] - stalled[-1]) < 3 * ms  # the burst took the stall's slots


def test_bag_export_writes_stills_as_numbered_files_of_the_recorded_bytes(bag: CompressedBag, tmp_path: Path) -> None:
    out = tmp_path / "stills"
    result = subprocess.run([CLI, "bag", "export", str(bag.path), STILLS, str(out)], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"Wrote {FRAMES} JPEG files of {STILLS} to {out}"), result.stdout
    assert sorted(p.name for p in out.iterdir()) == [f"{n:06d}.jpg" for n in range(1, FRAMES + 1)]
    assert [(out / f"{n:06d}.jpg").read_bytes() for n in range(1, FRAMES + 1)] == bag.jpegs
    again = subprocess.run([CLI, "bag", "export", str(bag.path), STILLS, str(out)], capture_output=True, text=True,
                           timeout=120)
    assert again.returncode == 1 and f"'{out}' exists" in again.stderr


def test_each_transport_is_played_decoded_on_its_image_topic() -> None:
    """image_transport's names (compressed, compressedDepth) and the encoder's (video) give the image topic back;
    any other compressed topic is played beside itself."""
    assert [decoded_name(f"/cam/image/{transport}") for transport in ("compressed", "compressedDepth", "video")] \
        == ["/cam/image"] * 3
    assert decoded_name("/cam/jpeg") == "/cam/jpeg/decoded"
