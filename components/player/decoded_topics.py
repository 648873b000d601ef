"""Decoding on the way back: compressed image topics of a bag played also as ``sensor_msgs/Image``.

With ``play.decode`` every played ``sensor_msgs/CompressedImage`` and ``foxglove_msgs/CompressedVideo`` topic is
decoded; with ``play.decode_topics`` only those named. A component written for raw frames then runs on a
compressed bag unchanged.

* **Names**: image_transport's layout, as its ``republish`` undoes it: ``<base>/compressed`` (and this
  project's ``<base>/video``) is decoded to ``<base>``; any other name to ``<topic>/decoded``. The compressed
  topic is still played as recorded. A decoded name that is already played (a raw topic recorded beside its
  compressed one), or that two compressed topics share, is a load error naming both.
* **Messages**: the original size, the encoding the JPEG/PNG ``format`` names (video: rgb8), the header stamp
  and frame_id of the compressed message (components/image_encoder/decoding.py). The QoS is the compressed
  topic's.
* **Where and when**: on a thread per compressed topic (decode_worker.py), fed by the read-ahead thread as it
  reads, in recorded order (a stream's decoder needs every access unit in turn): streams decode on all cores, since
  the codecs release the GIL, and ahead of playback, at most :data:`DECODE_AHEAD` messages of a stream waiting for
  their decoder; the read-ahead's byte bound counts the decoded pictures (each at the size of its stream's previous
  picture, known before it is decoded). The playback thread takes a picture when its message is due, waiting for
  it only if its decoder is late. Each pass (play, loop, seek) starts new decoders: a video stream gives frames
  from its first keyframe on, and counts the frames before it as skipped. A frame that fails to decode is counted
  and logged (once per kind of problem); the compressed message is still played, and the other streams go on.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import Image

from baglib.format.cdr_read import deserialize
from baglib.read.reader import BagMessage
from components.image_encoder import compressed_depth
from components.image_encoder._pyav import av
from components.image_encoder.decoding import DecodeCounts, StillDecoder, VideoDecoder
from components.player.decode_worker import Job, StreamWorker

#: The compressed types that decode, and whether they are video.
DECODABLE = {"sensor_msgs/msg/CompressedImage": False, "foxglove_msgs/msg/CompressedVideo": True}
#: Last name components that name a transport of the image topic before them (image_transport's and the
#: encoder's: components/image_encoder/compressed_depth.py).
TRANSPORTS = ("compressed", compressed_depth.TRANSPORT, "video")
#: Messages of one stream read and not decoded yet, at most: how far the reader may run ahead of a decoder.
DECODE_AHEAD = 8


def decoded_name(topic: str) -> str:
    """Where a compressed topic's images are played: its base for ``<base>/compressed``, ``<base>/compressedDepth``
    or ``<base>/video``."""
    base, _, last = topic.rpartition("/")
    return base if last in TRANSPORTS and base else f"{topic}/decoded"


def choose_topics(played: Mapping[str, str], decode: bool, named: list[str]) -> dict[str, str]:
    """Recorded topic -> decoded topic for what ``play.decode`` / ``play.decode_topics`` ask, from the played
    topics and their types; ValueError naming the parameter for a bad name or a clash."""
    parameter = "play.decode_topics" if named else "play.decode"
    for topic in named:
        if topic not in played:
            raise ValueError(f"parameter 'play.decode_topics': '{topic}' is not a played topic of the bag")
        if played[topic] not in DECODABLE:
            raise ValueError(f"parameter 'play.decode_topics': '{topic}' is a {played[topic]}, not one of "
                             f"{', '.join(DECODABLE)}")
    chosen = named or ([t for t, msgtype in played.items() if msgtype in DECODABLE] if decode else [])
    outputs: dict[str, str] = {}
    for topic in chosen:
        output = decoded_name(topic)
        clash = output if output in played else next((t for t, o in outputs.items() if o == output), None)
        if clash is not None:
            raise ValueError(f"parameter '{parameter}': '{topic}' would be decoded to '{output}', which "
                             f"'{clash}' is played on too; exclude one of them (play.exclude_topics_to_filter) "
                             "or choose the topics to decode with play.decode_topics")
        outputs[topic] = output
    return outputs


class DecodedStream:
    """One compressed topic's decoder (new for every pass) on a thread of its own, and the publisher of its images."""

    def __init__(self, node: Node, topic: str, output: str, video: bool, qos: QoSProfile,
                 msg_class: type, log_error: Callable[[str], None]) -> None:
        self.topic = topic
        self.output = output
        self.publisher = node.create_publisher(Image, output, qos)
        self.counts = DecodeCounts()
        self.published = 0
        self._video = video
        self._msg_class = msg_class
        self._log_error = log_error
        self._decoder: StillDecoder | VideoDecoder | None = None
        self._reported: set[str] = set()
        self._worker = StreamWorker(f"decode:{topic}", self._decode, DECODE_AHEAD)
        self._new_pass = True
        self._picture_bytes = 0   # of the last picture: what the next one is expected to take
        if video:
            # PyAV now, at load: its import is ~60 ms of Python holding the GIL, which at the first frame the
            # other streams' decoders and the playback thread would wait for (up to a second on a busy machine).
            av()

    def start_pass(self) -> None:
        """The next message begins a new pass; what the last pass left undecoded is dropped."""
        self._worker.cancel_pending()
        self._new_pass = True

    def submit(self, message: BagMessage) -> Job:
        """Hand ``message`` to this stream's thread (waiting while DECODE_AHEAD are in flight)."""
        job = Job(message, self._picture_bytes, self._new_pass)
        self._new_pass = False
        self._worker.submit(job)
        return job

    def end_pass(self) -> None:
        self._worker.end_pass()

    def close(self) -> None:
        self._worker.close()

    def _decode(self, job: Job) -> tuple[Any, Image | None]:
        """On the stream's thread: the compressed message object and its image (None: skipped or failed,
        counted)."""
        compressed = None
        try:
            compressed = deserialize(job.message.data, self._msg_class)
            if self._decoder is None or job.new_pass:
                self._decoder = VideoDecoder(compressed.format) if self._video else StillDecoder()
            image = self._decoder.decode(compressed)
        except Exception as exc:  # noqa: BLE001 - one frame a codec cannot take is counted, playback goes on
            self.counts.failed += 1
            self._report(str(exc))
            return compressed, None
        if image is None:
            self.counts.skipped += 1
        else:
            self.counts.decoded += 1
            self._picture_bytes = len(image.data)
        return compressed, image

    def publish(self, image: Image) -> None:
        self.publisher.publish(image)
        self.published += 1

    def stats(self) -> dict[str, Any]:
        return {"topic": self.output, **self.counts.__dict__}

    def _report(self, text: str) -> None:
        if text not in self._reported:
            self._reported.add(text)
            self._log_error(f"Cannot decode a message of '{self.topic}': {text} (counted as failed in "
                            "~/get_stats; the compressed message is played)")


class Decoding:
    """The decoded streams of a player, as the read-ahead thread and the playback thread use them."""

    def __init__(self, streams: list[DecodedStream]) -> None:
        self.streams = {stream.topic: stream for stream in streams}

    def start_pass(self) -> None:
        """A new pass over the bag (play, loop, seek): every stream waits for a keyframe again."""
        for stream in self.streams.values():
            stream.start_pass()

    def submit(self, message: BagMessage) -> Job | None:
        """For a decoded topic: the job its stream's thread decodes it in; None for any other topic."""
        stream = self.streams.get(message.connection.topic)
        return None if stream is None else stream.submit(message)

    def end_pass(self) -> None:
        """The pass is read: each stream's thread ends once its last messages are decoded."""
        for stream in self.streams.values():
            stream.end_pass()

    def close(self) -> None:
        """Stop every stream's thread (what is not decoded yet is dropped)."""
        for stream in self.streams.values():
            stream.close()

    def publish(self, topic: str, image: Image) -> None:
        self.streams[topic].publish(image)

    def stats(self) -> dict[str, dict[str, Any]]:
        return {topic: stream.stats() for topic, stream in self.streams.items()}
