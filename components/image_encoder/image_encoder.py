"""``components::ImageEncoder``: the container's camera images compressed, beside the drivers that publish them.

Loaded with ``use_intra_process_comms`` next to the cameras, it takes each ``sensor_msgs/Image`` by reference
(inline: the driver's ``publish()`` only queues it) and encodes it on a worker thread per topic
(:mod:`components.image_encoder.stream`), outside the executor. Output, per input topic ``<image>``:

* ``codec:=jpeg`` / ``png``: ``sensor_msgs/CompressedImage`` on ``<image>/compressed`` (image_transport's name);
* ``codec:=compressedDepth``: 16-bit depth as ``sensor_msgs/CompressedImage`` on ``<image>/compressedDepth``;
* ``codec:=h264`` / ``h265`` / ``av1`` or an FFmpeg encoder name: ``foxglove_msgs/CompressedVideo`` on
  ``<image>/video``.

``suffix`` replaces the last name part. Parameters (read-only; a bad one is a load error naming it):
``topics`` (list) and/or ``regex`` (topics of type sensor_msgs/msg/Image seen on the graph, looked for every
``polling_interval`` s), ``codec``, ``preset``, ``quality`` (JPEG quality, PNG level, or CRF; -1: the codec's
default), ``bitrate`` (bits/s, video, instead of quality), ``keyframe_interval`` (frames), ``width`` (output width,
0: the input's; the height keeps the aspect ratio).

Services: ``~/request_keyframe`` (std_srvs/Trigger: every video stream's next frame is a keyframe with its
parameter sets) and ``~/get_stats`` (std_srvs/Trigger, JSON counts per topic). ``/diagnostics`` shows the same
counts; skipped, rejected and stopped frames are its drops. Unloading logs each stream's final counts.

In-process readers (a recorder) find each output's stream through :mod:`components.image_encoder.outputs`.
"""
from __future__ import annotations

import functools
import json
import re
from typing import Any

from foxglove_msgs.msg import CompressedVideo
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CompressedImage, Image
from std_srvs.srv import Trigger

from component_container.component_node import ComponentNode
from component_container.health import DROPPED, OK, WARN, Health
from components.bounds import Bounds
from components.image_encoder import outputs
from components.image_encoder.codecs import check_codec, choose
from components.image_encoder.stream import EncodeStream
from components.node_parameters import clean, declare_defaults
from components.qos_profiles import absolute_topic

IMAGE_TYPE = "sensor_msgs/msg/Image"
DEFAULTS: dict[str, Any] = {
    "topics": [""], "regex": "", "codec": "jpeg", "preset": "", "quality": -1, "bitrate": 0,
    "keyframe_interval": 30, "width": 0, "suffix": "", "polling_interval": 1.0,
}
KEYFRAME_INTERVAL = Bounds(1, 10_000, "frames")
WIDTH = Bounds(2, 16384, "pixels")
BITRATE = Bounds(10_000, 1_000_000_000, "bits/s")
POLLING = Bounds(0.05, 60, "s")
#: Output QoS: reliable (a lost access unit spoils the video up to the next keyframe), which feeds best-effort
#: readers too; keep_last, so a slow reader never blocks the worker.
OUTPUT_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


class ImageEncoder(ComponentNode):
    """Compresses the container's camera images (module docstring)."""

    def __init__(self, node_name: str = "image_encoder", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._streams: dict[str, EncodeStream] = {}
        self._outputs: dict[str, Any] = {}  # per output topic, its publisher
        values = declare_defaults(self, DEFAULTS)
        self._topics = [absolute_topic(t) for t in clean(values["topics"])]
        try:
            self._regex = re.compile(values["regex"]) if values["regex"] else None
        except re.error as exc:
            raise ValueError(f"parameter 'regex': {values['regex']!r} is not a regular expression ({exc})") from None
        if not self._topics and self._regex is None:
            raise ValueError("parameters 'topics' / 'regex': name the image topics to encode")
        KEYFRAME_INTERVAL.check("'keyframe_interval'", values["keyframe_interval"])
        BITRATE.check("'bitrate'", values["bitrate"], zero_means="quality rules")
        POLLING.check("'polling_interval'", values["polling_interval"])
        self._choice = choose(values["codec"].strip().lower(), values["preset"], values["quality"],
                              values["bitrate"], values["keyframe_interval"])
        self._width = values["width"]
        WIDTH.check("'width'", self._width, zero_means="the input's width")
        if self._choice.is_video and self._width % 2:
            raise ValueError(f"parameter 'width': {self._width} is odd; {self._choice.codec} encodes 4:2:0, "
                             "which needs an even width")
        check_codec(self._choice)
        self._suffix = values["suffix"] or self._choice.transport
        if "/" in self._suffix:
            raise ValueError(f"parameter 'suffix': {self._suffix!r} must be one name part, without '/'")
        self._check_types(self._topics)
        for topic in self._topics:
            self._add_stream(topic)
        self._poll = (self.create_timer(values["polling_interval"], self._discover)
                      if self._regex is not None else None)
        self.create_service(Trigger, "~/request_keyframe", self._on_request_keyframe)
        self.create_service(Trigger, "~/get_stats", self._on_get_stats)

    # --- topics ----------------------------------------------------------------------------------------------
    def output_topic(self, topic: str) -> str:
        """Where the encoding of ``topic`` is published: ``<topic>/compressed`` or ``<topic>/video``."""
        return f"{topic.rstrip('/')}/{self._suffix}"

    def _check_types(self, topics: list[str]) -> None:
        """A named topic that exists with another type than Image is a load error (a non-image topic)."""
        known = dict(self.get_topic_names_and_types())
        for topic in topics:
            types = known.get(topic, [])
            if types and IMAGE_TYPE not in types:
                raise ValueError(f"parameter 'topics': {topic} carries {', '.join(types)}, not {IMAGE_TYPE}")

    def _discover(self) -> None:
        """Encode every new Image topic the regex matches (never the encoder's own outputs)."""
        assert self._regex is not None
        produced = {self.output_topic(t) for t in self._streams}
        for topic, types in self.get_topic_names_and_types():
            if (IMAGE_TYPE in types and topic not in self._streams and topic not in produced
                    and self._regex.search(topic)):
                self._add_stream(topic)

    def _add_stream(self, topic: str) -> None:
        msg_type = CompressedVideo if self._choice.is_video else CompressedImage
        output = self.output_topic(topic)
        stream = EncodeStream(topic, self._choice, self._width, functools.partial(self._publish, output),
                              self.get_logger().error,
                              subscribers=lambda: _subscriber_count(self._outputs[output]))
        self._streams[topic] = stream
        outputs.register(self._ipm, output, stream)  # known before the publisher puts the topic on the graph
        self._outputs[output] = self.create_publisher(msg_type, output, OUTPUT_QOS)
        # Inline: the driver's publish() only appends a reference to the stream's mailbox (never blocks).
        self.create_subscription(Image, topic, stream.offer, qos_profile_sensor_data, intra_process_inline=True)
        self.get_logger().info(f"Encoding {topic} as {self._choice.codec} on {self.output_topic(topic)}")

    def _publish(self, output: str, message: Any, keyframe: bool) -> None:
        self._outputs[output].publish(message)

    def encodes(self, topic: str) -> bool:
        """Whether ``topic`` is one of the image topics this encoder compresses (named, or matched by regex)."""
        return topic in self._topics or (self._regex is not None and self._regex.search(topic) is not None
                                         and not any(topic == self.output_topic(t) for t in self._streams))

    @property
    def is_video(self) -> bool:
        return self._choice.is_video

    # --- services and reporting ------------------------------------------------------------------------------
    def request_keyframe(self) -> int:
        """Every video stream's next frame becomes a keyframe; the number of streams asked."""
        for stream in self._streams.values():
            stream.request_keyframe()
        return len(self._streams) if self._choice.is_video else 0

    def _on_request_keyframe(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        asked = self.request_keyframe()
        response.success = self._choice.is_video
        response.message = (f"next frame of {asked} stream(s) is a keyframe" if self._choice.is_video
                            else f"{self._choice.codec} pictures are all self-contained")
        return response

    def stats(self) -> dict[str, Any]:
        """Counts per input topic: received, published, skipped (behind), rejected, stopped, rate_limited,
        keyframes, bytes, waiting."""
        return {"codec": self._choice.codec, "encoder": self._choice.encoder,
                "topics": {topic: stream.stats() for topic, stream in list(self._streams.items())}}

    def _on_get_stats(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = True, json.dumps(self.stats())
        return response

    def health(self) -> Health:
        """For /diagnostics: per topic its counts; WARN once frames were skipped or rejected."""
        topics = self.stats()["topics"]
        lost = sum(_lost(t) for t in topics.values())
        values = {DROPPED: str(lost)}
        for topic, t in sorted(topics.items()):
            values[topic] = _describe(t)
        if lost:
            return Health(WARN, f"{lost} frame(s) not encoded (skipped or rejected)", values)
        return Health(OK, f"encoding {len(topics)} topic(s) as {self._choice.codec}", values)

    def destroy_node(self) -> None:
        """Stop the workers (each finishes at most the frame it is encoding) and log their final counts, then
        the node."""
        for topic, stream in list(getattr(self, "_streams", {}).items()):
            stream.stop(self.shutdown_timeout)
            outputs.unregister(self._ipm, self.output_topic(topic), stream)
            counts = stream.stats()
            text = f"Encoded {topic} as {self._choice.codec}: {_describe(counts)}"
            if _lost(counts):  # rclpy's logger keeps one severity per call site: one call each
                self.get_logger().warning(text)
            else:
                self.get_logger().info(text)
        super().destroy_node()


def _lost(counts: dict[str, int]) -> int:
    """Frames a stream received and did not publish, but those left out by design (rate_limited)."""
    return counts["skipped"] + counts["rejected"] + counts["stopped"]


def _describe(counts: dict[str, int]) -> str:
    return (f"received {counts['received']}, published {counts['published']}, skipped {counts['skipped']} "
            f"(encoder behind), rejected {counts['rejected']}, stopped {counts['stopped']}, rate limited "
            f"{counts['rate_limited']}, keyframes {counts['keyframes']}, bytes {counts['bytes']}")


def _subscriber_count(publisher: Any) -> tuple[int, int]:
    """Readers of an output topic, (in-process, all); when either grows, the next frame is a keyframe.

    All readers are the larger of the in-process and the DDS count: an in-process subscription also has a DDS
    reader, matched later by discovery, which must not count as a second newcomer (nor ask for a second keyframe).
    The in-process count is watched on its own too: a reader unloaded a moment ago may still be matched over DDS,
    and would hide a new in-process reader from the larger count.
    """
    local = publisher.local_subscription_count() if hasattr(publisher, "local_subscription_count") else 0
    return local, max(local, getattr(publisher, "publisher", publisher).get_subscription_count())
