"""``components::Recorder`` as users run it: real container processes, real Fast DDS, real bag files.

One container ("the rig", started once per module) runs the camera, IMU and lidar drivers with intra-process
communication; each test loads a recorder next to them (``use_intra_process_comms``), drives it through its
services from a plain rclpy node in the test process, unloads it while the drivers keep running, and reads the
bag back with two independent readers: ``rosbags`` (mcap and sqlite3, decoded with the Jazzy typestore) and,
for MCAP, ``mcap`` + ``mcap_ros2``. A second container without intra-process communication publishes topics
that reach the recorder through DDS as raw CDR bytes.

What the drivers publish is known exactly: their sequence numbers (first 8 bytes of Image/PointCloud2 data,
``orientation_covariance[1]`` of Imu) and, for images and clouds, every byte of ``data``, which the tests
rebuild with the drivers' own ``make_image`` / ``make_cloud`` / ``make_imu`` on reference driver instances that
live in a private context on another ROS domain (never spun, invisible to the recorder).

Every container is stopped (by pid) and every tmpfs unmounted by the fixture or test that created it.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rcl_interfaces.srv import GetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosbag2_interfaces.msg import WriteSplitEvent
from rosbag2_interfaces.srv import IsPaused, Pause, Resume, Snapshot, SplitBagfile, TogglePaused
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import Image, Imu
from std_srvs.srv import Trigger

from components.camera_driver import CameraDriver
from components.imu_driver import ImuDriver
from components.lidar_driver import LidarDriver

from container_process import ContainerClient, small_filesystem
from ipc_testing import ContainerProcess, call, spin_for, wait_until
from ipc_testing.process_context import kept_context, process_context

REPO = Path(__file__).resolve().parents[1]
IPC = {"use_intra_process_comms": True}
#: Topics that are not the rig's: ROS infrastructure, and /chatter, which earlier test modules publish on this
#: test session's domain (a participant's endpoints can stay in the graph for its lease, 20 s, after it is gone).
NOT_INFRASTRUCTURE = "^/(rosout|parameter_events|diagnostics|events/.*|chatter)$"

CAMERA = {"width": 320, "height": 240, "fps": 30.0}
IMU = {"rate": 200.0}
LIDAR = {"points_per_scan": 4096, "rings": 16, "rate": 10.0}
EXT_IMU = {"rate": 100.0}
EXT_CAMERA = {"width": 160, "height": 120, "fps": 10.0}
HD_CAMERA = {"width": 1920, "height": 1080, "fps": 8.0}

RIG_TOPICS = ["/camera/image_raw", "/camera/camera_info", "/imu/imu", "/lidar/points"]
#: What a test waits for a recorder of the rig's topics to have written: a few periods of every driver.
RIG_MINIMUMS = {"/camera/image_raw": 4, "/camera/camera_info": 4, "/imu/imu": 20, "/lidar/points": 2}
EXT_TOPICS = ["/ext_imu/imu", "/ext_camera/image_raw", "/ext_camera/camera_info"]
SEQUENCED = {"sensor_msgs/msg/Image", "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/Imu"}

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


# --- containers -------------------------------------------------------------------------------------------
def Container(name: str, log_dir: Path, *args: str, fsize_limit: int | None = None,  # noqa: N802
              env: dict[str, str] | None = None) -> ContainerProcess:
    """A container named ``name`` with its log in ``log_dir`` (readable while it runs), started from the
    repository root; see :class:`ipc_testing.ContainerProcess` for ``fsize_limit`` (a full disk for it only)."""
    return ContainerProcess(*args, name=name, cwd=REPO, log_path=log_dir / f"{name}.log", fsize_limit=fsize_limit,
                            env=env)


SERVICES = {"pause": Pause, "resume": Resume, "toggle_paused": TogglePaused, "is_paused": IsPaused,
            "split_bagfile": SplitBagfile, "snapshot": Snapshot, "start_recording": Trigger,
            "stop_recording": Trigger, "get_stats": Trigger}
#: Requests that may be sent again until answered (a second one changes nothing); the others are sent once.
IDEMPOTENT = {"pause", "resume", "is_paused", "get_stats"}


class Recorder:
    """A recorder component loaded into a container, with clients of its services.

    The clients are created at load, before a test calls them: a service answers a new client only once it
    has matched the client's reply reader, and Fast DDS drops the reply otherwise ("failed to send response
    (timeout)"). Idempotent requests are sent again until answered (the first call of a test usually is one of
    them, get_stats); the others (split, toggle, stop...) are sent once, by then the clients created together
    have been matched.
    """

    def __init__(self, rig: "Rig", name: str, unique_id: int, uri: Path, loaded_ns: int) -> None:
        self.rig, self.name, self.unique_id, self.uri = rig, name, unique_id, uri
        self.loaded_ns = loaded_ns  # just before the load request
        self.unloaded_ns: int | None = None
        self.clients = {service: rig.probe.create_client(srv_type, f"/{name}/{service}")
                        for service, srv_type in SERVICES.items()}

    def service(self, srv_type: Any, service: str, request: Any = None, *, once: bool = False) -> Any:
        """Call one of the recorder's services; an idempotent one is sent again until answered, unless
        ``once`` (a resent request may be served after a later one from another client, see
        test_pause_resume_toggle)."""
        client = self.clients[service]
        assert client.srv_type is srv_type
        return call(self.rig.probe, client, request, again=service in IDEMPOTENT and not once)

    def destroy_clients(self) -> None:
        for client in self.clients.values():
            self.rig.probe.destroy_client(client)
        self.clients.clear()

    def trigger(self, service: str) -> Trigger.Response:
        return self.service(Trigger, service)

    def stats(self) -> dict[str, Any]:
        response = self.trigger("get_stats")
        assert response.success
        return json.loads(response.message)

    def is_paused(self) -> bool:
        return self.service(IsPaused, "is_paused").paused

    def wait_written(self, minimums: dict[str, int], timeout: float = 15.0) -> dict[str, dict[str, int]]:
        """Wait until the current bag holds at least ``minimums[topic]`` messages of each topic (a condition on
        the recorder's own counts, not a recording time); returns the per-topic counts."""
        def enough() -> dict[str, dict[str, int]] | None:
            topics = self.stats()["current"]["topics"]
            return topics if all(topics.get(t, {}).get("written", 0) >= n for t, n in minimums.items()) else None
        topics = wait_until(enough, timeout, interval=0.05)
        assert topics, f"{self.name}: {minimums} not written within {timeout} s: {self.stats()}"
        return topics

    def unload(self) -> None:
        response = self.rig.client.unload(self.unique_id)
        assert response.success, response.error_message
        self.unloaded_ns = time.time_ns()
        self.rig.loaded.remove(self)
        self.destroy_clients()


class Witness:
    """A plain subscription of the test process to a driver's topic: the (sequence number, capture stamp) of what
    it receives, in arrival order. What it saw before a request was sent was published before the request took
    effect; a message whose stamp is later than a moment was captured, hence published, after that moment
    (header stamps and ``time.time_ns()`` here read the same system clock). So the order of messages and service
    calls is established without assuming any rate or latency."""

    def __init__(self, node: Node, topic: str, msg_type: type) -> None:
        self.node, self.topic = node, topic
        self.seen: list[tuple[int, int]] = []
        self.subscription = node.create_subscription(
            msg_type, topic, self._received, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))

    def _received(self, msg: Any) -> None:
        seq = (int(msg.orientation_covariance[1]) if isinstance(msg, Imu)
               else int.from_bytes(bytes(msg.data[:8]), "little"))
        self.seen.append((seq, msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec))

    def captured_after(self, moment_ns: int, timeout: float = 10.0) -> int:
        """The sequence number of the first message received whose capture stamp is after ``moment_ns``."""
        def first() -> int | None:
            return next((seq for seq, stamp in self.seen if stamp > moment_ns), None)
        assert spin_for(self.node, timeout, lambda: first() is not None), \
            f"{self.topic}: nothing captured after {moment_ns} arrived within {timeout} s"
        seq = first()
        assert seq is not None
        return seq

    def destroy(self) -> None:
        self.node.destroy_subscription(self.subscription)


class Rig:
    """A container with drivers, a ContainerClient and the probe node the test process talks through."""

    def __init__(self, container: Container, probe: Node) -> None:
        self.container = container
        self.probe = probe
        self.client = ContainerClient(probe, container.name)
        self.client.wait()
        self.drivers: dict[str, int] = {}
        self.loaded: list[Recorder] = []

    def load_driver(self, plugin: str, name: str, parameters: dict[str, Any], ipc: bool = True,
                    package: str = "components") -> int:
        response = self.client.load(plugin, package, name=name, parameters=parameters, extra=IPC if ipc else None)
        assert response.success, response.error_message
        self.drivers[name] = response.unique_id
        return response.unique_id

    def unload_driver(self, name: str) -> None:
        assert self.client.unload(self.drivers.pop(name)).success

    def try_load_recorder(self, name: str, parameters: dict[str, Any],
                          plugin: tuple[str, str] = ("components", "components::Recorder")) -> Any:
        return self.client.load(plugin[1], plugin[0], name=name, parameters=parameters, extra=IPC)

    def record(self, name: str, uri: Path, *, plugin: tuple[str, str] = ("components", "components::Recorder"),
               **parameters: Any) -> Recorder:
        """Load a recorder (``plugin``: package and plugin name) writing to ``uri`` with ``parameters``
        (defaults: the rig's sensor topics)."""
        if not any(key in parameters for key in ("bag_name", "bag_file", "bag_prefix", "uri")):
            parameters.setdefault("storage.uri", str(uri))
        if not any(key in parameters for key in ("record.topics", "record.all_topics", "record_all",
                                                  "topics", "topic_names", "record.regex")):
            parameters["record.topics"] = RIG_TOPICS
        loaded_ns = time.time_ns()
        response = self.try_load_recorder(name, parameters, plugin)
        assert response.success, response.error_message
        assert response.full_node_name == f"/{name}"
        recorder = Recorder(self, name, response.unique_id, uri, loaded_ns)
        self.loaded.append(recorder)
        return recorder

    def listed(self) -> set[str]:
        return set(self.client.list().full_node_names)

    def cleanup(self) -> None:
        """Unload recorders a failed test left behind, so the next test starts from the plain rig."""
        for recorder in list(self.loaded):
            with contextlib.suppress(Exception):
                recorder.unload()
            recorder.destroy_clients()
        self.loaded.clear()


def start_rig(name: str, log_dir: Path, probe: Node, *, prefix: str = "", fsize_limit: int | None = None) -> Rig:
    """A container with camera, IMU and lidar (node names ``<prefix>camera`` ...: one domain, unique names)."""
    container = Container(name, log_dir, fsize_limit=fsize_limit)
    try:
        rig = Rig(container, probe)
        rig.load_driver("components::CameraDriver", f"{prefix}camera", CAMERA)
        rig.load_driver("components::ImuDriver", f"{prefix}imu", IMU)
        rig.load_driver("components::LidarDriver", f"{prefix}lidar", LIDAR)
    except BaseException:
        container.kill()
        raise
    return rig


# --- reference drivers: what the drivers publish, rebuilt by their own code -----------------------------------
#: The first of the domains the reference drivers use (up to 231, the last one Fast DDS can give ports to).
REFERENCE_DOMAINS = 200


class References:
    """Driver instances in a context of the process's own on another domain (kept, as every participant of a test
    process is: ipc_testing/process_context.py), used only for make_image & co."""

    def __init__(self) -> None:
        own = int(os.environ.get("ROS_DOMAIN_ID", "0"))
        # Never a test session's domain: those are 1..160 plus the worker index (conftest.py), these above.
        self.context = kept_context("references", domain_id=REFERENCE_DOMAINS + own % 32)
        self._drivers: dict[tuple, Any] = {}

    def driver(self, cls: type, **params: Any) -> Any:
        key = (cls, tuple(sorted(params.items())))
        if key not in self._drivers:
            overrides = [Parameter(k, value=v) for k, v in params.items()]
            self._drivers[key] = cls(f"reference_{len(self._drivers)}", context=self.context,
                                     parameter_overrides=overrides)
        return self._drivers[key]

    def close(self) -> None:
        for driver in self._drivers.values():
            driver.destroy_node()


# --- reading bags back ----------------------------------------------------------------------------------------
@dataclass
class Msg:
    """One message as a reader returned it."""

    topic: str
    type: str
    log_time: int
    publish_time: int | None
    size: int
    msg: Any

    @property
    def stamp(self) -> int:
        return self.msg.header.stamp.sec * 1_000_000_000 + self.msg.header.stamp.nanosec

    @property
    def seq(self) -> int:
        if self.type == "sensor_msgs/msg/Imu":
            return int(self.msg.orientation_covariance[1])
        return int.from_bytes(bytes(self.msg.data[:8]), "little")

    def key(self) -> tuple:
        """What both readers must agree on."""
        m = self.msg
        if self.type == "sensor_msgs/msg/Image":
            body: tuple = (m.height, m.width, m.encoding, m.step, m.is_bigendian, bytes(m.data))
        elif self.type == "sensor_msgs/msg/PointCloud2":
            body = (m.height, m.width, m.point_step, m.row_step, m.is_dense,
                    tuple((f.name, f.offset, f.datatype, f.count) for f in m.fields), bytes(m.data))
        elif self.type == "sensor_msgs/msg/Imu":
            body = (tuple(m.orientation_covariance), m.angular_velocity.z, m.linear_acceleration.z)
        elif self.type == "sensor_msgs/msg/CameraInfo":
            body = (m.height, m.width, m.distortion_model, tuple(m.k))
        else:
            body = ()
        header = (self.stamp, m.header.frame_id) if hasattr(m, "header") else ()
        return (self.topic, self.log_time, self.size, header, body)


def load_metadata(bag: Path) -> dict[str, Any]:
    return yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def read_rosbags(bag: Path) -> list[Msg]:
    out = []
    with Reader(bag) as reader:
        for connection, timestamp, raw in reader.messages():
            msg = TYPESTORE.deserialize_cdr(raw, connection.msgtype)
            out.append(Msg(connection.topic, connection.msgtype, timestamp, None, len(raw), msg))
    return out


def mcap_is_chunked(path: Path) -> bool:
    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    return summary is not None and bool(summary.chunk_indexes)


def read_mcap_file(path: Path) -> list[tuple[Msg, int, int]]:
    """(message, channel id, mcap sequence) in file order."""
    out = []
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            out.append((Msg(channel.topic, schema.name, message.log_time, message.publish_time,
                            len(message.data), decoded), channel.id, message.sequence))
    return out


@dataclass
class Bag:
    path: Path
    meta: dict[str, Any]
    messages: list[Msg]                                 # rosbags' reading, in log time order
    files: dict[str, list[Msg]] = field(default_factory=dict)  # mcap's reading per file, in file order

    def topic(self, name: str) -> list[Msg]:
        return [m for m in self.messages if m.topic == name]

    def seqs(self, name: str) -> list[int]:
        return [m.seq for m in self.topic(name)]

    def counts(self) -> dict[str, int]:
        return {t["topic_metadata"]["name"]: t["message_count"] for t in self.meta["topics_with_message_count"]}


def verify_bag(bag: Path, storage: str = "mcap", *, window: tuple[int, int] | None = None) -> Bag:
    """Read ``bag`` with every reader and check it is whole and consistent: counts, times, files."""
    meta = load_metadata(bag)
    assert meta["version"] == 9
    assert meta["storage_identifier"] == storage
    assert meta["ros_distro"] == "jazzy"
    extension = ".mcap" if storage == "mcap" else ".db3"
    assert meta["relative_file_paths"] == [f["path"] for f in meta["files"]]
    for index, name in enumerate(meta["relative_file_paths"]):
        assert name == f"{bag.name}_{index}{extension}"
        assert (bag / name).is_file()
    on_disk = sorted(p.name for p in bag.iterdir() if p.name != "metadata.yaml")
    assert on_disk == sorted(meta["relative_file_paths"]), "files on disk that metadata.yaml does not list"

    messages = read_rosbags(bag)
    for m in messages:
        assert m.topic in {t["topic_metadata"]["name"] for t in meta["topics_with_message_count"]}
    counts = defaultdict(int)
    for m in messages:
        counts[m.topic] += 1
    result = Bag(bag, meta, sorted(messages, key=lambda m: (m.log_time, m.topic)))
    assert {t: c for t, c in result.counts().items() if c} == dict(counts)
    assert meta["message_count"] == len(messages) == sum(f["message_count"] for f in meta["files"])
    if messages:
        first, last = min(m.log_time for m in messages), max(m.log_time for m in messages)
        assert meta["starting_time"]["nanoseconds_since_epoch"] == first
        assert meta["duration"]["nanoseconds"] == last - first
        if window is not None:
            assert window[0] <= first and last <= window[1], "log times outside the recording window"

    if storage == "mcap":
        from_mcap: list[Msg] = []
        for info in meta["files"]:
            rows = read_mcap_file(bag / info["path"])
            assert len(rows) == info["message_count"]
            if rows:
                times = [m.log_time for m, _, _ in rows]
                assert info["starting_time"]["nanoseconds_since_epoch"] == min(times)
                assert info["duration"]["nanoseconds"] == max(times) - min(times)
            last_sequence: dict[int, int] = {}
            times = [m.log_time for m, _, _ in rows]
            if not mcap_is_chunked(bag / info["path"]):  # unindexed files must be in log-time order; chunked
                # ones are indexed, and like rosbag2 the recorder writes them in arrival order
                assert times == sorted(times), f"{info['path']}: log times do not ascend in file order"
            for m, channel, sequence in rows:
                if sequence:  # 0, or increasing per channel
                    assert sequence > last_sequence.get(channel, 0)
                    last_sequence[channel] = sequence
                assert m.publish_time <= m.log_time, f"{m.topic}: publish time after log time"
                if m.type in SEQUENCED:
                    assert m.stamp <= m.publish_time, f"{m.topic}: header stamp after publish time"
            result.files[info["path"]] = [m for m, _, _ in rows]
            from_mcap.extend(m for m, _, _ in rows)
        # The two independent readers agree on every message, byte for byte where it matters.
        assert sorted(m.key() for m in from_mcap) == sorted(m.key() for m in messages)
    return result


def assert_contiguous(seqs: list[int], what: str) -> None:
    assert seqs, f"{what}: no messages"
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), \
        f"{what}: gaps or reordering: {missing(seqs)} missing"


def closing_stats(container: Container, uri: Path) -> dict[str, dict[str, int]]:
    """The per-topic counts of the recorder's closing log line for the bag at ``uri``."""
    pattern = re.compile(rf"Bag {re.escape(str(uri))} closed: [^\n]*\n((?:  /[^\n]*\n)*)")
    found = wait_until(lambda: pattern.findall(container.output), 5.0)
    assert found, f"no closing summary for {uri} in the container log:\n{container.output[-3000:]}"
    stats = {}
    for line in found[-1].splitlines():
        topic, received, written, dropped = re.fullmatch(
            r"  (\S+): received (\d+), written (\d+), dropped (\d+)", line).groups()
        stats[topic] = {"received": int(received), "written": int(written), "dropped": int(dropped)}
    return stats


def assert_complete(bag: "Bag", topic: str, stats: dict[str, dict[str, int]]) -> None:
    """Everything the recorder took in on ``topic`` is in the bag, in order, and any gap in the sequence
    numbers is one the recorder itself reports as dropped before its intake (none at these rates unless the
    machine stalls the container for longer than the subscription queue lasts)."""
    counts = stats[topic]
    messages = bag.topic(topic)
    assert counts["received"] == counts["written"] == len(messages) > 0, (topic, counts, len(messages))
    if messages[0].type not in SEQUENCED:
        return
    seqs = bag.seqs(topic)
    assert seqs == sorted(set(seqs)), f"{topic}: duplicates or reordering"
    lost = missing(seqs, limit=None)
    assert len(lost) <= counts["dropped"], f"{topic}: {lost[:20]} missing, {counts['dropped']} reported dropped"


def file_index(path: str) -> int:
    """N of a bag file ``<bag>_N.<extension>``."""
    return int(Path(path).stem.rsplit("_", 1)[1])


def missing(seqs: list[int], limit: int | None = 20) -> list[int]:
    return sorted(set(range(min(seqs), max(seqs) + 1)) - set(seqs))[:limit]


def runs(seqs: list[int]) -> list[tuple[int, int]]:
    """Maximal runs of consecutive numbers as (first, last)."""
    out: list[tuple[int, int]] = []
    for s in seqs:
        if out and s == out[-1][1] + 1:
            out[-1] = (out[-1][0], s)
        else:
            out.append((s, s))
    return out


def check_driver_content(bag: Bag, refs: References, prefix: str = "", camera: dict = CAMERA,
                         lidar: dict | None = LIDAR, imu: dict | None = IMU) -> None:
    """Every recorded image/cloud/IMU message is exactly what the driver built for that sequence number."""
    cam = refs.driver(CameraDriver, **camera)
    images = bag.topic(f"/{prefix}camera/image_raw")
    assert images
    for m in images:
        expected = cam.make_image(m.seq, m.stamp)
        assert m.size == len(serialize_message(expected))
        assert (m.msg.height, m.msg.width, m.msg.encoding, m.msg.step) == \
            (expected.height, expected.width, expected.encoding, expected.step)
        assert m.msg.header.frame_id == "camera"
        assert bytes(m.msg.data) == expected.data.tobytes(), f"image {m.seq}: data differs from the driver's"
    stamps = {m.stamp for m in images}
    infos = bag.topic(f"/{prefix}camera/camera_info")
    # The two topics are subscribed one after the other, so either may start (and end) a few frames earlier;
    # inside the span both cover, every camera_info belongs to a recorded image.
    inside = [m for m in infos if min(stamps) <= m.stamp <= max(stamps)]
    assert inside and all(m.stamp in stamps for m in inside), "camera_info stamps do not match image stamps"
    if lidar is not None:
        lid = refs.driver(LidarDriver, **lidar)
        clouds = bag.topic(f"/{prefix}lidar/points")
        assert clouds
        for m in clouds:
            expected = lid.make_cloud(m.seq, m.stamp)
            assert m.size == len(serialize_message(expected))
            assert bytes(m.msg.data) == expected.data.tobytes(), f"cloud {m.seq}: data differs"
            assert [f.name for f in m.msg.fields] == [f.name for f in expected.fields]
    if imu is not None:
        ref = refs.driver(ImuDriver, **imu)
        samples = bag.topic(f"/{prefix}imu/imu")
        assert samples
        for m in samples:
            expected = ref.make_imu(m.seq, m.stamp)
            assert list(m.msg.orientation_covariance) == list(expected.orientation_covariance)
            assert (m.msg.angular_velocity.z, m.msg.linear_acceleration.z) == \
                (expected.angular_velocity.z, expected.linear_acceleration.z)


# --- fixtures -------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def probe() -> Iterator[Node]:
    node = Node("recorder_test_probe", context=process_context())
    yield node
    node.destroy_node()


@pytest.fixture(scope="module")
def log_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("container_logs")


@pytest.fixture(scope="module")
def refs() -> Iterator[References]:
    references = References()
    yield references
    references.close()


@pytest.fixture(scope="module")
def external(log_dir: Path, probe: Node) -> Iterator[Rig]:
    """A second container without intra-process communication: its topics reach recorders over DDS only."""
    container = Container("recorder_test_external", log_dir)
    try:
        rig = Rig(container, probe)
        rig.load_driver("components::ImuDriver", "ext_imu", EXT_IMU, ipc=False)
        rig.load_driver("components::CameraDriver", "ext_camera", EXT_CAMERA, ipc=False)
        yield rig
    finally:
        container.stop()  # SIGINT (a clean exit leaves no stale endpoints in the graph); killed if it hangs


@pytest.fixture(scope="module")
def rig_module(log_dir: Path, probe: Node) -> Iterator[Rig]:
    rig = start_rig("recorder_test_rig", log_dir, probe)
    try:
        yield rig
    finally:
        rig.cleanup()
        assert rig.container.stop() == 0, rig.container.output[-3000:]


@pytest.fixture()
def rig(rig_module: Rig) -> Iterator[Rig]:
    """The shared rig; after each test it must still be alive with its drivers, and no recorder left."""
    yield rig_module
    rig_module.cleanup()
    assert rig_module.container.alive(), rig_module.container.output[-3000:]
    assert {"/camera", "/imu", "/lidar"} <= rig_module.listed()


@pytest.fixture()
def split_events(probe: Node) -> Iterator[list[WriteSplitEvent]]:
    events: list[WriteSplitEvent] = []
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    subscription = probe.create_subscription(WriteSplitEvent, "/events/write_split", events.append, qos)
    yield events
    probe.destroy_subscription(subscription)


# --- the recording itself ---------------------------------------------------------------------------------------
#: What the main test waits for the recorder to have written of each topic: a few periods of every driver.
MAIN_MINIMUMS = {"/camera/image_raw": 4, "/camera/camera_info": 4, "/imu/imu": 25, "/lidar/points": 3,
                 "/ext_imu/imu": 12, "/ext_camera/image_raw": 3, "/ext_camera/camera_info": 3}


def test_records_intra_process_and_dds_topics_into_one_bag(rig: Rig, external: Rig, refs: References,
                                                           tmp_path: Path) -> None:
    uri = tmp_path / "rig_bag"
    recorder = rig.record("recorder_main", uri, **{"record.all_topics": True,
                                                  "record.exclude_regex": NOT_INFRASTRUCTURE})
    # Topics of the other process are found by graph discovery, which may take a moment.
    assert wait_until(lambda: set(RIG_TOPICS + EXT_TOPICS) <= set(recorder.stats()["current"]["topics"]), 10.0)
    recorder.wait_written(MAIN_MINIMUMS)
    recorder.unload()
    assert {"/camera", "/imu", "/lidar"} <= rig.listed() and "/recorder_main" not in rig.listed()
    assert rig.container.alive()

    bag = verify_bag(uri, window=(recorder.loaded_ns, recorder.unloaded_ns))
    assert set(bag.counts()) == set(RIG_TOPICS) | set(EXT_TOPICS)
    types = {t["topic_metadata"]["name"]: t["topic_metadata"] for t in bag.meta["topics_with_message_count"]}
    assert types["/camera/image_raw"]["type"] == "sensor_msgs/msg/Image"
    assert types["/imu/imu"]["type_description_hash"].startswith("RIHS01_")
    assert types["/lidar/points"]["offered_qos_profiles"][0]["reliability"] == "reliable"

    # Moderate rates: nothing lost on any topic, in-process or over DDS.
    stats = closing_stats(rig.container, uri)
    assert set(stats) == set(RIG_TOPICS) | set(EXT_TOPICS)
    for topic in RIG_TOPICS:
        assert_complete(bag, topic, stats)
    for topic in EXT_TOPICS:
        assert stats[topic]["received"] == stats[topic]["written"] == bag.counts()[topic]
    for topic in ("/ext_imu/imu", "/ext_camera/image_raw"):
        assert_contiguous(bag.seqs(topic), topic)
    for topic, minimum in MAIN_MINIMUMS.items():
        assert len(bag.topic(topic)) >= minimum, f"{topic}: {len(bag.topic(topic))} messages, {minimum} were written"
    check_driver_content(bag, refs)
    check_driver_content(bag, refs, "ext_", camera=EXT_CAMERA, lidar=None, imu=EXT_IMU)

    # In-process messages carry the delivery time as both stamps (unless the recorder had to move the log time
    # up to keep the file in time order); DDS ones the writer's source timestamp, strictly before reception:
    # the two paths really were the two paths.
    mcap_messages = [m for rows in bag.files.values() for m in rows]
    local = [m for m in mcap_messages if m.topic in RIG_TOPICS]
    assert sum(m.publish_time == m.log_time for m in local) >= 0.8 * len(local), "not delivered in-process"
    assert all(m.publish_time < m.log_time for m in mcap_messages if m.topic in EXT_TOPICS), "not over DDS"

    # The drivers kept running after the recorder was unloaded.
    last_imu = max(bag.seqs("/imu/imu"))
    later: list[int] = []
    subscription = rig.probe.create_subscription(
        Imu, "/imu/imu", lambda msg: later.append(int(msg.orientation_covariance[1])), 50)
    try:
        assert spin_for(rig.probe, 10.0, lambda: len(later) >= 5), "the IMU driver stopped with the recorder"
    finally:
        rig.probe.destroy_subscription(subscription)
    assert min(later) > last_imu


def test_full_hd_camera_at_moderate_rate(rig: Rig, refs: References, tmp_path: Path) -> None:
    rig.load_driver("components::CameraDriver", "hd_camera", HD_CAMERA)
    try:
        uri = tmp_path / "hd"
        recorder = rig.record("recorder_hd", uri,
                              **{"record.topics": ["/hd_camera/image_raw", "/hd_camera/camera_info"]})
        recorder.wait_written({"/hd_camera/image_raw": 5})
        stop = recorder.trigger("stop_recording")
        recorder.unload()
    finally:
        rig.unload_driver("hd_camera")
    assert stop.success, stop.message
    stats = json.loads(stop.message)
    bag = verify_bag(uri)
    seqs = bag.seqs("/hd_camera/image_raw")
    assert_contiguous(seqs, "1080p images")
    assert len(seqs) >= 5
    assert stats["topics"]["/hd_camera/image_raw"] == {"received": len(seqs), "written": len(seqs),
                                                       "dropped": 0, "queue_dropped": 0, "rate_limited": 0, "repeated": 0}
    assert stats["error"] is None and stats["bytes_written"] == (uri / "hd_0.mcap").stat().st_size
    cam = refs.driver(CameraDriver, **HD_CAMERA)
    for m in bag.topic("/hd_camera/image_raw"):
        assert (m.msg.width, m.msg.height, len(m.msg.data)) == (1920, 1080, 1920 * 1080 * 3)
        assert bytes(m.msg.data) == cam.make_image(m.seq, m.stamp).data.tobytes()


# --- services -------------------------------------------------------------------------------------------------
def test_stop_and_start_recording_make_a_second_bag(rig: Rig, tmp_path: Path) -> None:
    uri = tmp_path / "session"
    topics = {"/imu/imu": Imu, "/camera/image_raw": Image}
    witnesses = {topic: Witness(rig.probe, topic, msg_type) for topic, msg_type in topics.items()}
    try:
        recorder = rig.record("recorder_stopstart", uri, **{"record.topics": list(topics)})
        recorder.wait_written({"/imu/imu": 20, "/camera/image_raw": 3})
        stop = recorder.trigger("stop_recording")
        stopped = time.time_ns()
        assert stop.success, stop.message
        first_stats = json.loads(stop.message)
        assert first_stats["bag"] == str(uri) and first_stats["error"] is None
        first = verify_bag(uri)  # finalized while the recorder is still loaded
        again = recorder.trigger("stop_recording")
        assert not again.success and "not recording" in again.message
        stats = recorder.stats()
        assert stats["recording"] is False and len(stats["finished"]) == 1

        # Messages published while stopped (captured after the stop, seen before the start) are in neither bag.
        between = {topic: witness.captured_after(stopped) for topic, witness in witnesses.items()}
        start = recorder.trigger("start_recording")
        assert start.success, start.message
        second_uri = tmp_path / "session_1"
        assert str(second_uri) in start.message
        assert recorder.trigger("start_recording").success is False
        recorder.wait_written({"/imu/imu": 20, "/camera/image_raw": 3})
        recorder.unload()
    finally:
        for witness in witnesses.values():
            witness.destroy()
    second = verify_bag(second_uri)
    assert first.meta["relative_file_paths"] == ["session_0.mcap"]
    assert second.meta["relative_file_paths"] == ["session_1_0.mcap"]
    second_stats = closing_stats(rig.container, second_uri)
    for topic in topics:
        assert_complete(first, topic, first_stats["topics"])
        assert_complete(second, topic, second_stats)
        assert max(first.seqs(topic)) < between[topic] < min(second.seqs(topic)), (topic, between[topic])
    assert first.messages[-1].log_time < second.messages[0].log_time


def test_pause_resume_toggle(rig: Rig, tmp_path: Path) -> None:
    """What is published while paused is skipped, what is published before and after is all recorded. The
    witnesses tell which messages were published in which phase (see :class:`Witness`). Each state change is
    sent once: a resent ~/pause could be served after the ~/toggle_paused that follows it (another client), and
    pause the recorder again. The clients were created at load, so the recorder has long matched them."""
    uri = tmp_path / "paused"
    topics = {"/imu/imu": Imu, "/camera/image_raw": Image}
    minimums = {"/imu/imu": 20, "/camera/image_raw": 3}
    witnesses = {topic: Witness(rig.probe, topic, msg_type) for topic, msg_type in topics.items()}

    def captured_after(moment: int) -> dict[str, int]:
        return {topic: witness.captured_after(moment) for topic, witness in witnesses.items()}

    try:
        recorder = rig.record("recorder_pause", uri, **{"record.start_paused": True, "record.topics": list(topics)})
        loaded = time.time_ns()
        assert recorder.is_paused() is True
        while_start_paused = captured_after(loaded)
        assert all(t["written"] == 0 for t in recorder.stats()["current"]["topics"].values())
        resume_sent = time.time_ns()
        recorder.service(Resume, "resume", once=True)
        resumed = time.time_ns()
        assert recorder.is_paused() is False
        while_recording = captured_after(resumed)
        recorder.wait_written(minimums)
        recorder.service(Pause, "pause", once=True)
        paused_at = time.time_ns()
        assert recorder.is_paused() is True
        recorder.service(Pause, "pause", once=True)  # pausing twice is harmless
        while_paused = captured_after(paused_at)
        toggle_sent = time.time_ns()
        recorder.service(TogglePaused, "toggle_paused")
        toggled = time.time_ns()
        assert recorder.is_paused() is False
        after_toggle = captured_after(toggled)
        written = recorder.stats()["current"]["topics"]
        recorder.wait_written({topic: written[topic]["written"] + n for topic, n in minimums.items()})
        recorder.service(TogglePaused, "toggle_paused")
        assert recorder.is_paused() is True
        recorder.unload()
    finally:
        for witness in witnesses.values():
            witness.destroy()

    bag = verify_bag(uri)
    for m in bag.messages:
        assert m.log_time >= resume_sent, "recorded while start_paused"
        assert not paused_at < m.log_time < toggle_sent, f"{m.topic} {m.seq} recorded while paused"
    stats = closing_stats(rig.container, uri)
    for topic in topics:
        seqs = bag.seqs(topic)
        assert stats[topic]["received"] == stats[topic]["written"] == len(seqs)
        before = [s for m, s in zip(bag.topic(topic), seqs) if m.log_time <= paused_at]
        after = [s for m, s in zip(bag.topic(topic), seqs) if m.log_time >= toggle_sent]
        assert len(before) + len(after) == len(seqs)
        assert len(before) >= minimums[topic] and len(after) >= minimums[topic], (len(before), len(after))
        # Each recorded stretch is whole (up to what the recorder reports dropped before its intake) ...
        assert len(missing(before, None)) + len(missing(after, None)) <= stats[topic]["dropped"], runs(seqs)
        # ... it holds what was published while recording, and the pause skipped what was published while paused.
        assert while_start_paused[topic] < before[0], (topic, while_start_paused[topic], runs(seqs))
        assert while_recording[topic] in before, (topic, while_recording[topic], runs(seqs))
        assert before[-1] < while_paused[topic] < after[0], (topic, while_paused[topic], runs(seqs))
        assert after_toggle[topic] in after, (topic, after_toggle[topic], runs(seqs))


def test_split_bagfile_service_and_events(rig: Rig, split_events: list[WriteSplitEvent], tmp_path: Path) -> None:
    uri = tmp_path / "split"
    recorder = rig.record("recorder_split", uri, **{"record.topics": ["/imu/imu", "/camera/image_raw"]})
    assert spin_for(rig.probe, 10.0, lambda: any(
        p.node_name == "recorder_split" for p in rig.probe.get_publishers_info_by_topic("/events/write_split")))

    def write_some() -> None:  # into the current file: a few messages of each topic more than so far
        topics = recorder.stats()["current"]["topics"]
        recorder.wait_written({topic: topics.get(topic, {}).get("written", 0) + more
                               for topic, more in (("/imu/imu", 10), ("/camera/image_raw", 2))})

    write_some()
    recorder.service(SplitBagfile, "split_bagfile")
    write_some()
    recorder.service(SplitBagfile, "split_bagfile")
    write_some()
    recorder.unload()
    spin_for(rig.probe, 5.0, lambda: len([e for e in split_events if e.node_name == "/recorder_split"]) >= 3)

    bag = verify_bag(uri)
    names = [f"split_{i}.mcap" for i in range(3)]
    assert bag.meta["relative_file_paths"] == names
    assert all(info["message_count"] > 0 for info in bag.meta["files"])
    stats = closing_stats(rig.container, uri)
    for topic in ("/imu/imu", "/camera/image_raw"):
        assert_complete(bag, topic, stats)  # nothing lost at the splits
        per_file = [[m.seq for m in bag.files[name] if m.topic == topic] for name in names]
        assert all(per_file) and per_file[0][-1] < per_file[1][0] and per_file[1][-1] < per_file[2][0]
    events = [(e.closed_file, e.opened_file) for e in split_events if e.node_name == "/recorder_split"]
    paths = [str(uri / name) for name in names]
    assert events == [(paths[0], paths[1]), (paths[1], paths[2]), (paths[2], "")]


def test_max_bagfile_size_splits(rig: Rig, split_events: list[WriteSplitEvent], tmp_path: Path) -> None:
    uri = tmp_path / "sized"
    limit = 1_000_000
    recorder = rig.record("recorder_sized", uri, **{"record.topics": ["/camera/image_raw", "/imu/imu"],
                                                    "storage.max_bagfile_size": limit})
    # ~230 kB per image: a split every few images; the fifth file is open once four are full
    assert wait_until(lambda: file_index(recorder.stats()["current"]["current_file"]) >= 4, 15.0, interval=0.05), \
        recorder.stats()
    recorder.unload()
    bag = verify_bag(uri)
    files = bag.meta["relative_file_paths"]
    assert len(files) >= 5, f"only {files} with a 1 MB limit"
    frame = CAMERA["width"] * CAMERA["height"] * 3
    for name in files[:-1]:
        size = (uri / name).stat().st_size
        assert limit <= size <= limit + 2 * frame + 200_000, f"{name}: {size} bytes for a {limit} byte limit"
    stats = closing_stats(rig.container, uri)
    assert_complete(bag, "/camera/image_raw", stats)
    assert_complete(bag, "/imu/imu", stats)
    spin_for(rig.probe, 3.0, lambda: any(e.node_name == "/recorder_sized" and not e.opened_file
                                          for e in split_events))
    events = [(Path(e.closed_file).name, Path(e.opened_file).name if e.opened_file else "")
              for e in split_events if e.node_name == "/recorder_sized"]
    assert events == list(zip(files, [*files[1:], ""]))


def test_get_stats_live_counts(rig: Rig, tmp_path: Path) -> None:
    uri = tmp_path / "stats"
    recorder = rig.record("recorder_stats", uri)
    recorder.wait_written({topic: 1 for topic in RIG_TOPICS})
    first = recorder.stats()
    def grew(now: dict[str, Any]) -> bool:
        """Every topic received more, and the writer wrote more (it may lag what was received)."""
        return now["current"]["bytes_written"] > first["current"]["bytes_written"] and all(
            counts["received"] > first["current"]["topics"][topic]["received"]
            for topic, counts in now["current"]["topics"].items())

    # a condition on the counts, not a time
    assert wait_until(lambda: grew(recorder.stats()), 15.0, interval=0.05)
    second = recorder.stats()
    assert first["recording"] and not first["paused"] and first["current"]["error"] is None
    assert first["current"]["bag"] == str(uri)
    assert first["current"]["current_file"] == str(uri / "stats_0.mcap")
    assert set(first["current"]["topics"]) == set(RIG_TOPICS)
    for topic in RIG_TOPICS:
        before, after = first["current"]["topics"][topic], second["current"]["topics"][topic]
        assert after["received"] > before["received"] > 0
        assert before["written"] <= before["received"] and after["dropped"] == after["queue_dropped"]
    assert second["current"]["bytes_written"] > first["current"]["bytes_written"] > 0
    assert recorder.service(Snapshot, "snapshot").success is False  # not in snapshot mode

    stop = recorder.trigger("stop_recording")
    final = recorder.stats()
    assert final["recording"] is False and final["current"] is None
    bag = verify_bag(uri)
    finished = final["finished"][0]["topics"]
    assert json.loads(stop.message)["topics"] == finished
    assert {t: c["written"] for t, c in finished.items()} == bag.counts()
    for topic in RIG_TOPICS:
        assert_complete(bag, topic, finished)
    recorder.unload()


def test_snapshot_mode_writes_the_ring(rig: Rig, tmp_path: Path) -> None:
    uri = tmp_path / "snap"
    cache = 3_000_000
    recorder = rig.record("recorder_snap", uri, **{"record.topics": ["/camera/image_raw", "/imu/imu"],
                                                   "storage.snapshot_mode": True,
                                                   "storage.max_cache_size": cache})
    frame = CAMERA["width"] * CAMERA["height"] * 3

    def camera() -> dict[str, int]:
        return recorder.stats()["current"]["topics"].get("/camera/image_raw", {"received": 0, "written": 0})

    # More images than the ring holds, so that it has dropped its oldest ones
    assert wait_until(lambda: camera()["received"] > cache // frame + 5, 15.0, interval=0.05), recorder.stats()
    before = recorder.stats()["current"]["topics"]
    assert all(t["written"] == 0 for t in before.values()), "snapshot mode wrote before a snapshot"
    witness = Witness(rig.probe, "/camera/image_raw", Image)
    try:  # an image published before the snapshot (seen before it was asked for): it or a newer one ends the bag
        newest_before = witness.captured_after(time.time_ns())
    finally:
        witness.destroy()
    assert recorder.service(Snapshot, "snapshot").success is True
    snapshot_done = time.time_ns()
    assert wait_until(lambda: camera()["written"] > 0, 5.0)
    received = camera()["received"]  # more arrives in the ring; without another snapshot it is never written
    assert wait_until(lambda: camera()["received"] >= received + 5, 10.0, interval=0.05)
    recorder.unload()
    bag = verify_bag(uri)
    images = bag.topic("/camera/image_raw")
    assert 3 <= len(images) <= cache // frame, f"{len(images)} images from a {cache} byte ring"
    stats = closing_stats(rig.container, uri)
    for topic in ("/camera/image_raw", "/imu/imu"):  # the ring holds the newest messages, none missing
        assert len(missing(bag.seqs(topic), None)) <= stats[topic]["dropped"], runs(bag.seqs(topic))
    assert all(m.log_time <= snapshot_done for m in bag.messages), "written after the snapshot"
    assert images[-1].seq >= newest_before, f"the ring lost its newest images: {runs(bag.seqs('/camera/image_raw'))}"


# --- storage options ------------------------------------------------------------------------------------------
def test_sqlite3_storage(rig: Rig, refs: References, tmp_path: Path) -> None:
    uri = tmp_path / "db"
    recorder = rig.record("recorder_sqlite", uri, **{"storage.storage_id": "sqlite3"})
    recorder.wait_written(RIG_MINIMUMS)
    recorder.unload()
    bag = verify_bag(uri, "sqlite3", window=(recorder.loaded_ns, recorder.unloaded_ns))
    assert bag.meta["relative_file_paths"] == ["db_0.db3"]
    assert not list(uri.glob("*-wal")) and not list(uri.glob("*-journal"))
    stats = closing_stats(rig.container, uri)
    for topic in ("/camera/image_raw", "/imu/imu", "/lidar/points"):
        assert_complete(bag, topic, stats)
    check_driver_content(bag, refs)


@pytest.mark.parametrize("preset", ["zstd_fast", "fastwrite"])
def test_mcap_storage_presets(rig: Rig, refs: References, tmp_path: Path, preset: str) -> None:
    uri = tmp_path / preset
    recorder = rig.record(f"recorder_{preset}", uri, **{"storage.storage_preset_profile": preset})
    recorder.wait_written(RIG_MINIMUMS)
    recorder.unload()
    bag = verify_bag(uri)
    stats = closing_stats(rig.container, uri)
    for topic in ("/camera/image_raw", "/imu/imu", "/lidar/points"):
        assert_complete(bag, topic, stats)
    check_driver_content(bag, refs)
    with open(uri / f"{preset}_0.mcap", "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    if preset == "zstd_fast":
        assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {"zstd"}
        raw = sum(c.uncompressed_size for c in summary.chunk_indexes)
        assert sum(c.compressed_size for c in summary.chunk_indexes) < raw
    else:
        assert not summary.chunk_indexes


# --- stopping the container -----------------------------------------------------------------------------------
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_container_signal_finalizes_the_bag(probe: Node, log_dir: Path, tmp_path: Path, sig: int) -> None:
    name = f"recorder_test_{sig.name.lower()}"
    container = Container(name, log_dir)
    imu, camera = f"/{sig.name.lower()}_imu/imu", f"/{sig.name.lower()}_camera/image_raw"  # the rig has /imu
    try:
        rig = Rig(container, probe)
        rig.load_driver("components::ImuDriver", f"{sig.name.lower()}_imu", IMU)
        rig.load_driver("components::CameraDriver", f"{sig.name.lower()}_camera", CAMERA)
        uri = tmp_path / "signalled"
        rig.record("recorder", uri, **{"record.topics": [imu, camera]}).wait_written({imu: 20, camera: 3})
        code = container.stop(sig)
    finally:
        container.kill()
    log = container.output
    assert code == 0, log[-3000:]
    assert re.search(r"Shutting down \(SIG(INT|TERM)\): unloading all components", log), log
    bag = verify_bag(uri)
    stats = closing_stats(container, uri)
    assert_complete(bag, imu, stats)
    assert_complete(bag, camera, stats)
    assert len(bag.seqs(imu)) >= 20 and len(bag.seqs(camera)) >= 3


# --- failures ---------------------------------------------------------------------------------------------------
def test_existing_uri_is_refused(rig: Rig, tmp_path: Path) -> None:
    uri = tmp_path / "taken"
    uri.mkdir()
    (uri / "keep.txt").write_text("mine")
    response = rig.try_load_recorder("recorder_taken", {"storage.uri": str(uri), "record.topics": RIG_TOPICS})
    assert response.success is False
    assert str(uri) in response.error_message and "already exists" in response.error_message
    assert sorted(p.name for p in uri.iterdir()) == ["keep.txt"] and (uri / "keep.txt").read_text() == "mine"
    assert "/recorder_taken" not in rig.listed()


@pytest.mark.parametrize("where", ["under_a_file", "proc"])
def test_unwritable_uri_is_refused(rig: Rig, tmp_path: Path, where: str) -> None:
    if where == "under_a_file":
        (tmp_path / "plain_file").write_text("")
        uri = tmp_path / "plain_file" / "bag"
    else:
        uri = Path("/proc") / f"recorder_test_bag_{os.getpid()}"
    response = rig.try_load_recorder("recorder_unwritable", {"storage.uri": str(uri), "record.topics": RIG_TOPICS})
    assert response.success is False
    assert "cannot create bag directory" in response.error_message and str(uri) in response.error_message
    assert not uri.exists()
    assert "/recorder_unwritable" not in rig.listed()


def test_disk_full_stops_recording_cleanly(probe: Node, rig: Rig, log_dir: Path, tmp_path: Path) -> None:
    size = 3 * 1024 * 1024
    with small_filesystem(tmp_path / "small", size) as mounted, contextlib.ExitStack() as stack:
        prefix = ""
        if mounted:
            target = rig
        else:  # no tmpfs here: a container whose files may not grow beyond the size
            prefix = "fsize_"
            target = start_rig("recorder_test_fsize", log_dir, probe, prefix=prefix, fsize_limit=size)
            stack.callback(target.container.kill)
        topics = [f"/{prefix}{topic[1:]}" for topic in RIG_TOPICS]
        drivers = {f"/{prefix}{name}" for name in ("camera", "imu", "lidar")}
        imu = f"/{prefix}imu/imu"
        uri = tmp_path / "small" / "full"
        # No free-space guard: this test is about the disk really running full (test_disk_guard.py is the guard)
        recorder = target.record("recorder_full", uri, **{"record.topics": topics, "storage.min_free_space": 0})
        error = wait_until(lambda: recorder.stats()["current"]["error"], 15.0, interval=0.2)
        assert error, "the recorder never noticed the full disk"
        assert re.search(r"No space left on device|File too large", error), error
        log = wait_until(lambda: "stopped:" in target.container.output and target.container.output, 5.0)
        assert log and re.search(rf"\[recorder_full\]: Recording to {re.escape(str(uri))} stopped: .*"
                                 r"(No space left on device|File too large)", log), target.container.output[-3000:]
        # The container and the drivers carry on; the recorder keeps counting what it can no longer write.
        received = recorder.stats()["current"]["topics"][imu]["received"]
        after = wait_until(lambda: (s := recorder.stats())["current"]["topics"][imu]["received"] > received + 5
                           and s, 10.0, interval=0.05)
        assert after, f"the recorder stopped counting {imu} after the failure: {recorder.stats()}"
        assert after["current"]["topics"][imu]["dropped"] > 0
        assert target.container.alive() and drivers | {"/recorder_full"} <= target.listed()
        recorder.unload()
        assert target.container.alive() and drivers <= target.listed()

        bag = verify_bag(uri, window=(recorder.loaded_ns, recorder.unloaded_ns))
        assert bag.meta["message_count"] > 0
        written = sum((uri / name).stat().st_size for name in bag.meta["relative_file_paths"])
        assert written <= size
        assert re.search(rf"Bag {re.escape(str(uri))} closed: \d+ messages, \d+ bytes, error: ",
                         target.container.output)
        stats = closing_stats(target.container, uri)
        for topic in topics:
            # Written up to the failure: a whole prefix; everything else is counted as dropped.
            assert stats[topic]["written"] == len(bag.topic(topic))
            assert stats[topic]["received"] + after["current"]["topics"][topic]["queue_dropped"] <= \
                stats[topic]["written"] + stats[topic]["dropped"]
            if bag.topic(topic) and topic != f"/{prefix}camera/camera_info":
                seqs = bag.seqs(topic)
                queue_dropped = after["current"]["topics"][topic]["queue_dropped"]
                assert len(missing(seqs, None)) <= queue_dropped, f"{topic}: {missing(seqs)} missing"
        if not mounted:
            assert target.container.stop() == 0


# --- parameters -----------------------------------------------------------------------------------------------
def test_parameter_aliases(rig: Rig, tmp_path: Path) -> None:
    uri = tmp_path / "aliased"
    recorder = rig.record("recorder_aliases", uri, **{
        "record_all": True, "exclude": r"^(?!/imu/imu$)",  # every topic but the rig's IMU
        "bag_name": str(uri), "storage_id": "sqlite3", "max_bag_duration": 1.0})
    names = ["storage.uri", "storage.storage_id", "record.all_topics", "storage.max_bagfile_duration"]
    client = rig.probe.create_client(GetParameters, "/recorder_aliases/get_parameters")
    values = call(rig.probe, client, GetParameters.Request(names=names)).values
    rig.probe.destroy_client(client)
    assert [values[0].string_value, values[1].string_value, values[2].bool_value, values[3].double_value] == \
        [str(uri), "sqlite3", True, 1.0], "alias values are mirrored to their rosbag2 parameter names"
    # the first split comes once the IMU's messages span more than the 1 s of max_bag_duration
    assert wait_until(lambda: file_index(recorder.stats()["current"]["current_file"]) >= 1, 15.0, interval=0.05), \
        recorder.stats()
    recorder.wait_written({"/imu/imu": recorder.stats()["current"]["topics"]["/imu/imu"]["written"] + 5})
    recorder.unload()
    bag = verify_bag(uri, "sqlite3")
    assert set(bag.counts()) == {"/imu/imu"}
    assert len(bag.meta["relative_file_paths"]) >= 2, "max_bag_duration 1 s did not split"
    assert_complete(bag, "/imu/imu", closing_stats(rig.container, uri))
    for info in bag.meta["files"][:-1]:
        assert info["duration"]["nanoseconds"] <= 1e9


@pytest.mark.parametrize("parameters, expected", [
    ({"bag_name": "{uri}", "storage.uri": "{uri}_other"}, "'bag_name' is an alias of 'storage.uri'"),
    ({"storage.storage_id": "foo"}, "parameter 'storage.storage_id' must be one of mcap, sqlite3, got 'foo'"),
    ({"storage_id": "foo"},
     "parameter 'storage_id' (alias of 'storage.storage_id') must be one of mcap, sqlite3, got 'foo'"),
    ({"storage.max_cache_size": 0}, "parameter 'storage.max_cache_size' must be in [1, "),
    ({"storage.storage_preset_profile": "turbo"}, "storage_preset_profile 'turbo'"),
    # aliases have the types of their rosbag2 names
    ({"record_all": "false"}, "parameter 'record_all' (alias of 'record.all_topics') must be a boolean"),
    ({"start_recording_immediately": "false"},
     "parameter 'start_recording_immediately' (alias of 'record.start_paused') must be a boolean"),
    ({"max_bag_size": True}, "parameter 'max_bag_size' (alias of 'storage.max_bagfile_size') must be a number"),
    ({"max_cache_size": 1.9}, "parameter 'max_cache_size' (alias of 'storage.max_cache_size') must be a number "
                              "(integer), got 1.9"),
    ({"storage.uri": 7}, "parameter 'storage.uri' must be a string, got 7"),
    ({"exclude": "(/imu"}, "parameter 'exclude' (alias of 'record.exclude_regex') is not a valid regular "
                           "expression"),
    ({"record.regex": "[a"}, "parameter 'record.regex' is not a valid regular expression"),
], ids=["alias_and_name", "storage_id", "storage_id_alias", "cache_size", "preset", "record_all_string",
        "start_immediately_string", "bag_size_bool", "cache_size_float", "uri_int", "exclude_regex", "regex"])
def test_bad_parameters_are_refused(rig: Rig, tmp_path: Path, parameters: dict[str, Any], expected: str) -> None:
    uri = tmp_path / "never"
    parameters = {k: v.format(uri=uri) if isinstance(v, str) else v for k, v in parameters.items()}
    parameters.setdefault("storage.uri", str(uri))
    parameters["record.topics"] = RIG_TOPICS
    response = rig.try_load_recorder("recorder_bad", parameters)
    assert response.success is False
    assert expected in response.error_message, response.error_message
    assert not uri.exists() and not Path(f"{uri}_other").exists()
    assert "/recorder_bad" not in rig.listed()


def test_not_set_means_default_and_unknown_names_are_reported(rig: Rig, tmp_path: Path) -> None:
    uri = tmp_path / "hygiene"
    recorder = rig.record("recorder_hygiene", uri, **{
        "storage.uri": None, "bag_name": str(uri),  # NOT_SET (as a launch file's None sends it): the default
        "record.topic": ["/imu/imu"], "max_bag_sise": 5, "record.topics": ["/imu/imu"]})
    recorder.wait_written({"/imu/imu": 5})
    recorder.unload()
    assert set(verify_bag(uri).counts()) == {"/imu/imu"}
    # the container's warning, as for any component: aliases given are declared, so only the unknown are named
    warnings = re.findall(r"\[recorder_hygiene\]: \S+ does not declare the parameters (.*): ignored", rig.container.output)
    assert warnings == ["'record.topic' (did you mean 'record.topics'?), 'max_bag_sise'"]
