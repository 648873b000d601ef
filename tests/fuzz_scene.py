"""The fuzz scenario shared by tests/test_fuzz.py and benchmarks/fuzz_load.py.

A container (``--use-intra-process-comms --bag-root``, a fresh temporary working directory) runs a small
camera, an IMU and a recorder of both; then seeded random LoadNode / UnloadNode requests and recorder
service calls are sent through a :class:`~fuzz_pipeline.Pipeline`; afterwards every component a random
request loaded is unloaded. What to check afterwards (alive, rates, bag, RSS, files) is measured here and
judged by the caller.
"""
from __future__ import annotations

import os
import pathlib
import random
import time
import uuid
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from composition_interfaces.srv import LoadNode, UnloadNode
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rosbags.rosbag2 import Reader
from sensor_msgs.msg import Image, Imu
from std_msgs.msg import String

from baglib.format.cdr_fast import serialize
from baglib.format.metadata import TopicInfo
from baglib.write.writer import BagWriter

from container_process import ContainerClient, ContainerProcess, listing, proc_status, wait_until
from fuzz_pipeline import LATE, Pipeline, PipelineCounts
from fuzz_requests import MARKER, RECORDER_SERVICES, REPLAY_BAG, RequestGenerator

CAMERA = ("components::CameraDriver", "fuzz_cam", {"width": 160, "height": 120, "fps": 30.0})
IMU = ("components::ImuDriver", "fuzz_imu", {"rate": 100.0})
RATES = {"/fuzz_cam/image_raw": (Image, 30.0), "/fuzz_imu/imu": (Imu, 100.0)}
RECORDER = "fuzz_recorder"
# Beyond this many live fuzz components the next request unloads one: a fuzz-loaded driver may publish at up to
# 10 kHz, and a few of them would starve the 2-core machine the test runs on.
MAX_FUZZ_LOADED = 3
OPERATIONS = (("load", 0.40), ("unload", 0.25), ("recorder", 0.35))


def environment_seed() -> int:
    """``IPC_FUZZ_SEED`` to replay a run, else a fresh random seed."""
    return int(os.environ.get("IPC_FUZZ_SEED") or random.SystemRandom().randrange(2**32))


def file_listing(root: pathlib.Path, skip: pathlib.Path | None = None) -> set[str]:
    """Every path under ``root`` (relative), except the tree ``skip``; unreadable corners are ignored."""
    paths = set()
    for directory, dirs, files in os.walk(root, onerror=lambda _error: None):
        here = pathlib.Path(directory)
        dirs[:] = [d for d in dirs if skip is None or here / d != skip]
        paths.update(str((here / name).relative_to(root)) for name in dirs + files)
    return paths


def marked_paths(root: pathlib.Path, skip: pathlib.Path, marker: str) -> set[str]:
    """Paths under ``root`` (outside ``skip``) whose name carries ``marker``: an escaped write."""
    return {path for path in file_listing(root, skip) if marker in pathlib.Path(path).name}


def rss_bytes(pid: int) -> int:
    return int(proc_status(pid)["VmRSS"].split()[0]) * 1024


@dataclass
class FuzzReport:
    """What the random requests got."""

    seed: int
    requests: int
    seconds: float = 0.0
    counts: PipelineCounts = field(default_factory=PipelineCounts)
    loaded: int = 0
    load_errors: Counter = field(default_factory=Counter)
    internal_errors: list[str] = field(default_factory=list)
    recorder_failures: Counter = field(default_factory=Counter)

    def add(self, other: "FuzzReport") -> None:
        """Take in another run's report (the same scene, the next part of a run)."""
        self.requests += other.requests
        self.seconds += other.seconds
        self.counts.add(other.counts)
        self.loaded += other.loaded
        self.load_errors.update(other.load_errors)
        self.internal_errors.extend(other.internal_errors)
        self.recorder_failures.update(other.recorder_failures)

    def summary(self) -> str:
        errors = "\n".join(f"    {count:6d}  {message}" for message, count in self.load_errors.most_common(12))
        return (f"seed {self.seed}: {self.requests} requests in {self.seconds:.1f} s "
                f"({self.requests / max(self.seconds, 1e-9):.0f}/s); sent {self.counts.sent}, "
                f"answered {self.counts.answered}, later than {LATE:g} s {self.counts.late}, no reply "
                f"{self.counts.abandoned}, slowest reply (s) "
                f"{ {kind: round(seconds, 2) for kind, seconds in self.counts.slowest.items()} }; {self.loaded} loads "
                f"succeeded; recorder services answering failure: {dict(self.recorder_failures)}; internal "
                f"errors {len(self.internal_errors)}\n  most frequent load errors:\n{errors}")


def write_replay_bag(path: pathlib.Path) -> None:
    """A small finished bag for fuzzed players: 50 strings on /fuzz_chatter over 5 s."""
    with BagWriter(path) as writer:
        writer.add_topic(TopicInfo("/fuzz_chatter", "std_msgs/msg/String"))
        for n in range(50):
            stamp = 1_700_000_000_000_000_000 + n * 100_000_000
            writer.write("/fuzz_chatter", bytes(serialize(String(data=f"fuzz {n}"))), stamp, stamp)


class FuzzScene:
    """The container with its drivers and recorder; a context manager that always stops the container."""

    def __init__(self, node: Node, workdir: pathlib.Path) -> None:
        self.node = node
        self.cwd = workdir / "cwd"
        self.bag_root = workdir / "bags"
        self.cwd.mkdir()
        self.bag_root.mkdir()
        self.process = ContainerProcess("--use-intra-process-comms", "--bag-root", str(self.bag_root),
                                        cwd=str(self.cwd))
        self.client = ContainerClient(node)
        self.protected: dict[int, str] = {}
        self.marker = f"{MARKER}{uuid.uuid4().hex[:8]}"

    def __enter__(self) -> "FuzzScene":
        self.process.__enter__()
        try:
            self.client.wait(timeout=30.0)
        except AssertionError:
            raise AssertionError(f"container did not come up:\n{self.process.output}") from None
        write_replay_bag(self.bag_root / REPLAY_BAG)
        for plugin, name, parameters in (CAMERA, IMU):
            self._load(plugin, name, parameters)
        self._load("components::Recorder", RECORDER, {"storage.uri": str(self.bag_root / "baseline_bag"),
                                                       "record.topics": list(RATES)})
        return self

    def __exit__(self, *exc: Any) -> None:
        self.process.__exit__(*exc)

    def _load(self, plugin: str, name: str, parameters: dict[str, Any]) -> None:
        response = self.client.load(plugin, name=name, parameters=parameters)
        assert response.success, (plugin, response.error_message, self.process.output)
        self.protected[response.unique_id] = response.full_node_name

    # --- the random requests ----------------------------------------------------------------------------
    def fuzz(self, seed: int, requests: int, fuzz_node: Node, max_in_flight: int = 32) -> FuzzReport:
        """Send ``requests`` random requests, pipelined; every fuzz-loaded component is unloaded after."""
        rng = random.Random(seed)
        generator = RequestGenerator(rng, self.bag_root, self.marker)
        report = FuzzReport(seed, requests)
        pipeline = Pipeline(fuzz_node, max_in_flight)
        prefix = "/ComponentManager/_container"
        # Replies of up to max_in_flight calls can arrive in one burst: a client's default depth of 10 would let
        # its reader drop some (keep_last), and each such call would then wait out the pipeline's timeout.
        replies = QoSProfile(depth=4 * max_in_flight)
        load = fuzz_node.create_client(LoadNode, f"{prefix}/load_node", qos_profile=replies)
        unload = fuzz_node.create_client(UnloadNode, f"{prefix}/unload_node", qos_profile=replies)
        recorder = {name: fuzz_node.create_client(srv_type, f"/{RECORDER}/{name}", qos_profile=replies)
                    for name, srv_type in RECORDER_SERVICES.items()}
        loaded: list[int] = []

        def on_load(response: LoadNode.Response) -> None:
            if response.success:
                report.loaded += 1
                loaded.append(response.unique_id)
                return
            report.load_errors[_shape(response.error_message)] += 1
            if "Internal error" in response.error_message:
                report.internal_errors.append(response.error_message)

        def on_unload(unique_id: int) -> Any:
            def handle(response: UnloadNode.Response) -> None:
                if unique_id in loaded and (response.success or "No node found" in response.error_message):
                    loaded.remove(unique_id)
                if "Internal error" in response.error_message:
                    report.internal_errors.append(response.error_message)
            return handle

        def on_recorder(service: str) -> Any:
            def handle(response: Any) -> None:
                if getattr(response, "success", True) is False:
                    report.recorder_failures[service] += 1
            return handle

        _warm_up(pipeline, [(load, LoadNode.Request()), (unload, UnloadNode.Request())]
                 + [(client, client.srv_type.Request()) for client in recorder.values()])
        start = time.monotonic()
        names, weights = zip(*OPERATIONS)
        for _ in range(requests):
            operation = "unload" if len(loaded) > MAX_FUZZ_LOADED else rng.choices(names, weights)[0]
            if operation == "load":
                pipeline.submit(load, generator.load(), "load", on_load)
            elif operation == "unload":
                request = generator.unload(loaded, set(self.protected))
                pipeline.submit(unload, request, "unload", on_unload(request.unique_id))
            else:
                service, request = generator.recorder_call()
                pipeline.submit(recorder[service], request, service, on_recorder(service), timeout=5.0)
        pipeline.drain()
        report.seconds = time.monotonic() - start
        report.counts = pipeline.counts
        pipeline.close()
        for client in [load, unload, *recorder.values()]:
            fuzz_node.destroy_client(client)
        self.unload_fuzz_components()
        return report

    def unload_fuzz_components(self) -> None:
        for unique_id, _name in listing(self.client):
            if unique_id not in self.protected:
                response = self.client.unload(unique_id)
                assert response.success or "No node found" in response.error_message, response

    # --- afterwards -------------------------------------------------------------------------------------
    def message_rates(self, seconds: float = 3.0) -> dict[str, float]:
        """Messages per second a plain rclpy subscriber receives on each driver topic."""
        counts = {topic: 0 for topic in RATES}
        subscriptions = [self.node.create_subscription(
            msg_type, topic, lambda _msg, topic=topic: counts.__setitem__(topic, counts[topic] + 1), 10)
            for topic, (msg_type, _rate) in RATES.items()]
        wait_until(lambda: all(counts.values()), 10.0, self.node)  # discovery
        for topic in counts:
            counts[topic] = 0
        start = time.monotonic()
        wait_until(lambda: False, seconds, self.node)
        elapsed = time.monotonic() - start
        for subscription in subscriptions:
            self.node.destroy_subscription(subscription)
        return {topic: count / elapsed for topic, count in counts.items()}

    def fresh_sequences(self, count: int = 5, timeout: float = 30.0) -> dict[str, list[int]]:
        """The drivers' sequence numbers (Imu ``orientation_covariance[1]``, Image ``data[0:8]``) of the first
        ``count`` messages a plain rclpy subscriber receives on each driver topic from now on; fewer if the
        generous ``timeout`` passes first (a driver that stopped)."""
        sequences: dict[str, list[int]] = {topic: [] for topic in RATES}

        def on_message(topic: str, msg: Any) -> None:
            if isinstance(msg, Imu):
                sequences[topic].append(int(msg.orientation_covariance[1]))
            else:
                sequences[topic].append(int.from_bytes(bytes(msg.data[:8]), "little"))

        subscriptions = [self.node.create_subscription(
            msg_type, topic, lambda msg, topic=topic: on_message(topic, msg), 10)
            for topic, (msg_type, _rate) in RATES.items()]
        try:
            wait_until(lambda: all(len(seqs) >= count for seqs in sequences.values()), timeout, self.node)
        finally:
            for subscription in subscriptions:
                self.node.destroy_subscription(subscription)
        return sequences

    def finish_recorder(self) -> None:
        recorder_id = next(uid for uid, name in self.protected.items() if name == f"/{RECORDER}")
        response = self.client.unload(recorder_id)
        assert response.success, response

    def escaped(self, root: pathlib.Path) -> set[str]:
        """Files and directories under ``root`` that fuzz paths named, outside the bag root."""
        return marked_paths(root, self.bag_root, self.marker)

    def bags(self) -> dict[str, int]:
        """Messages in every finished bag under the bag root (read by rosbags), by bag directory."""
        counts = {}
        for metadata in sorted(self.bag_root.rglob("metadata.yaml")):
            with Reader(metadata.parent) as reader:
                counts[str(metadata.parent.relative_to(self.bag_root))] = reader.message_count
        return counts


def _shape(message: str) -> str:
    """An error message with its quoted values cut, so that messages group by kind."""
    return message.split("'")[0][:90]


def _warm_up(pipeline: Pipeline, calls: list[tuple[Any, Any]]) -> None:
    """Call each service until it answers once: the fuzz must not start while replies to this node are lost."""
    for client, request in calls:
        answered: list[Any] = []
        deadline = time.monotonic() + 30.0
        while not answered:
            assert time.monotonic() < deadline, f"{client.srv_name} never answered"
            pipeline.submit(client, request, "warm-up", answered.append, timeout=0.5)
            pipeline.drain()
