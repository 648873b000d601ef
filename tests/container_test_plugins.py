"""Components used only by the container tests, loaded as ``tests.container_test_plugins:<Class>`` into a
container started with ``--allow-module-plugins`` and the repository root as its working directory.
"""
from __future__ import annotations

import functools
import hashlib
import json
import pathlib
import sys
import threading
import time
from typing import Any

from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from component_container.component_node import ComponentNode
from baglib.format.message_definitions import message_class
from baglib.write.writer import BagWriter
from baglib.format.cdr_fast import CdrData, serialize
from components.recorder.recorder import Recorder


class ThrowingComponent(Node):
    """A component whose constructor raises after the node exists and has a publisher and a timer."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("throwing_component", **kwargs)
        self._publisher = self.create_publisher(String, "thrower_output", 10)
        self._timer = self.create_timer(0.05, lambda: self._publisher.publish(String(data="ghost")))
        raise RuntimeError("deliberate failure in ThrowingComponent.__init__")


class BlockingComponent(Node):
    """A timer callback that blocks: touches ``marker`` (if set), then sleeps ``block_seconds``, or, with ``gate``
    set, waits for as long as the file ``gate`` exists (returning at once when it does not). Then, with a
    marker, it writes ``<marker>.done``: ``alive`` if its node was still alive, else ``destroyed``."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("blocking_component", **kwargs)
        self.block_seconds = self.declare_parameter("block_seconds", 5.0).value
        self.marker = self.declare_parameter("marker", "").value
        self.gate = self.declare_parameter("gate", "").value
        self._timer = self.create_timer(0.05, self._block)

    def _block(self) -> None:
        if self.gate and not pathlib.Path(self.gate).exists():
            return
        if self.marker:
            pathlib.Path(self.marker).write_text(str(time.monotonic()))
        if self.gate:
            while pathlib.Path(self.gate).exists():
                time.sleep(0.01)
        else:
            time.sleep(self.block_seconds)
        if self.marker:
            try:
                with self.handle:
                    state = "alive"
            except Exception:  # noqa: BLE001 - InvalidHandle: destroyed under the running callback
                state = "destroyed"
            pathlib.Path(self.marker + ".done").write_text(state)


class LoggingComponent(Node):
    """Logs one DEBUG and one INFO line per tick, for three ticks, naming itself; then touches ``marker`` (if
    set): once it exists, every line this component was going to log has been logged."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("logging_component", **kwargs)
        self.marker = self.declare_parameter("marker", "").value
        self._ticks = 0
        self._timer = self.create_timer(0.05, self._log)

    def _log(self) -> None:
        self._ticks += 1
        if self._ticks > 3:
            return
        self.get_logger().debug(f"debug-probe from {self.get_name()}")
        self.get_logger().info(f"info-probe from {self.get_name()}")
        if self._ticks == 3 and self.marker:
            pathlib.Path(self.marker).touch()


class GuardedComponent(Node):
    """A component with a guard condition (rclpy's EventsExecutor cannot run it)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("guarded_component", **kwargs)
        self._guard = self.create_guard_condition(lambda: None)


class NotANode:
    """Not an rclpy Node: the container must refuse to load it."""


class SlowPublisher(Node):
    """A timer callback that takes a while and then publishes: unloading it nearly always meets it running."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("slow_publisher", **kwargs)
        self.hold = self.declare_parameter("hold", 0.05).value
        self._publisher = self.create_publisher(String, "slow_output", 10)
        self._timer = self.create_timer(0.01, self._tick)

    def _tick(self) -> None:
        time.sleep(self.hold)
        self._publisher.publish(String(data="slow"))


class RaisingComponent(Node):
    """Publishes on ``raising_output`` at 20 Hz and raises from its timer callback at tick ``raise_after``."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("raising_component", **kwargs)
        self.raise_after = self.declare_parameter("raise_after", 5).value
        self._publisher = self.create_publisher(String, "raising_output", 10)
        self._ticks = 0
        self._timer = self.create_timer(0.05, self._tick)

    def _tick(self) -> None:
        self._ticks += 1
        if self._ticks == self.raise_after:
            raise RuntimeError("deliberate failure in RaisingComponent's timer callback")
        self._publisher.publish(String(data=str(self._ticks)))


class SelfDestroyingComponent(Node):
    """Destroys its own node from its first timer callback (it is no longer running after that)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("self_destroying", **kwargs)
        self._timer = self.create_timer(0.05, self.destroy_node)


class ExitingConstructor(Node):
    """Calls sys.exit() in its constructor."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("exiting_constructor", **kwargs)
        sys.exit(3)


class BadDestructor(Node):
    """A publisher, and a destroy_node that raises before destroying anything."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("bad_destructor", **kwargs)
        self._publisher = self.create_publisher(String, "bad_destructor_output", 10)

    def destroy_node(self) -> None:
        raise RuntimeError("deliberate failure in BadDestructor.destroy_node")


class HangingDestructor(Node):
    """A destroy_node that never returns (a disk that hangs, say)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("hanging_destructor", **kwargs)

    def destroy_node(self) -> None:
        threading.Event().wait()


class ReusingPublisher(ComponentNode):
    """Publishes ONE std_msgs/String object ``count`` times on ``reused``, setting its data to 0, 1, 2...
    before each publish, all from one callback (a burst the subscribers cannot have finished with)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("reusing_publisher", **kwargs)
        self.count = self.declare_parameter("count", 100).value
        self.delay = self.declare_parameter("delay", 1.0).value
        self._publisher = self.create_publisher(String, "reused", 1000)
        self._message = String()
        self._timer = self.create_timer(self.delay, self._burst)

    def _burst(self) -> None:
        self._timer.cancel()
        for index in range(self.count):
            self._message.data = str(index)
            self._publisher.publish(self._message)

class BrokenImagePublisher(ComponentNode):
    """Publishes ``count`` small images on ``~/image_raw`` once someone subscribes, numbered by the first 8 bytes
    of ``data``; image number ``broken`` claims a height no uint32 holds (field checks are off by default in
    Jazzy, so nothing stops it before a serializer does)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("broken_image_publisher", **kwargs)
        self._count = self.declare_parameter("count", 30).value
        self._broken = self.declare_parameter("broken", 10).value
        self._sent = 0
        self._publisher = self.create_publisher(Image, "~/image_raw", 100)
        self._timer = self.create_timer(0.02, self._publish)

    def _publish(self) -> None:
        if self._sent >= self._count or self._publisher.get_subscription_count() == 0:
            return
        image = Image(height=8, width=16, encoding="mono8", step=16,
                      data=self._sent.to_bytes(8, "little") + bytes(120))
        image.header.frame_id = "broken_camera"
        image.header.stamp = self.get_clock().now().to_msg()
        if self._sent == self._broken:
            image.height = 2**40
        self._publisher.publish(image)
        self._sent += 1


class HangingBagWriter(BagWriter):
    """A bag on a disk that hangs: after ``HANG_AFTER`` messages a write never returns, holding the writer's
    lock as a write stuck in the kernel would."""

    HANG_AFTER = 20

    def write(self, topic: str, data: CdrData, log_time_ns: int, publish_time_ns: int,
              split: bool | None = None) -> None:
        if self.message_count >= self.HANG_AFTER:
            with self._lock:
                threading.Event().wait()
        super().write(topic, data, log_time_ns, publish_time_ns, split)


class HangingDiskRecorder(Recorder):
    """The recorder, writing to a disk that hangs (see HangingBagWriter)."""

    writer_class = HangingBagWriter


class CrashingBagWriter(BagWriter):
    """A writer with a bug: writing a message on ``CRASH_TOPIC`` raises something no storage error handler expects."""

    CRASH_TOPIC = "/writer_crash"

    def write(self, topic: str, data: CdrData, log_time_ns: int, publish_time_ns: int,
              split: bool | None = None) -> None:
        if topic == self.CRASH_TOPIC:
            raise RuntimeError(f"deliberate bug in the writer, on {topic}")
        super().write(topic, data, log_time_ns, publish_time_ns, split)


class CrashingWriterRecorder(Recorder):
    """The recorder, with a writer that has a bug (see CrashingBagWriter)."""

    writer_class = CrashingBagWriter


class GatedBagWriter(BagWriter):
    """A bag whose writes wait while a gate file ``<bag directory>.hold`` exists: a test holds the writer busy
    for as long as it needs and lets it go by removing the file."""

    def write(self, topic: str, data: CdrData, log_time_ns: int, publish_time_ns: int,
              split: bool | None = None) -> None:
        gate = self.path.with_name(self.path.name + ".hold")
        while gate.exists():
            time.sleep(0.01)
        super().write(topic, data, log_time_ns, publish_time_ns, split)


class GatedRecorder(Recorder):
    """The recorder, writing through a GatedBagWriter."""

    writer_class = GatedBagWriter


class PlaybackProbe(ComponentNode):
    """An in-process consumer for player tests: subscribes to ``topics`` (with ``types``, reliable keep_all
    unless ``best_effort``) and answers ``~/report`` (std_srvs/Trigger) with JSON per topic: receive times
    (monotonic ns), the SHA-1 of each message's exact CDR (baglib.format.cdr_fast: what a recorder writes) and the
    Python types of ``data`` fields."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("playback_probe", **kwargs)
        topics = self.declare_parameter("topics", [""]).value
        types = self.declare_parameter("types", [""]).value
        self._lock = threading.Lock()
        self._seen: dict[str, dict[str, list[Any]]] = {}
        qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
        self._inputs: list[Any] = []
        for topic, type_name in zip(topics, types):
            if not topic:
                continue
            msg_class = message_class(type_name)
            self._seen[topic] = {"times": [], "digests": [], "data_types": []}
            self._inputs.append(self.create_subscription(
                msg_class, topic, functools.partial(self._on_message, topic), qos))
        self._report = self.create_service(Trigger, "~/report", self._on_report)

    def _on_message(self, topic: str, msg: Any) -> None:
        now = time.monotonic_ns()
        digest = hashlib.sha1(bytes(serialize(msg))).hexdigest()
        with self._lock:
            seen = self._seen[topic]
            seen["times"].append(now)
            seen["digests"].append(digest)
            if hasattr(msg, "data") and len(seen["data_types"]) < 3:
                seen["data_types"].append(type(msg.data).__name__)

    def _on_report(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            response.success, response.message = True, json.dumps(self._seen)
        return response
