"""Video channels: each camera also as H.264 (or the chosen codec), encoded only while a client watches.

For every advertised ``sensor_msgs/msg/Image`` topic ``<image>`` the bridge offers ``<image>/video``, schema
``foxglove_msgs/msg/CompressedVideo`` (``ros2msg``, message encoding ``cdr``, like its other channels, and
what ``components::ImageEncoder`` publishes and the recorder stores), which the Foxglove Image panel plays.
Where the graph already has a topic of that name (an ImageEncoder publishes it), that topic is the channel.

A :class:`VideoFeed` is the intake of such a channel, in place of a ChannelQueue. While a client is subscribed
the bridge subscribes to the image topic (in-process frames by reference, inline) and the feed runs an
:class:`~components.image_encoder.stream.EncodeStream`, the ImageEncoder's worker and codecs: frames admitted by
the rate limit (``video.max_rate``, by the images' header stamps) go to its bounded mailbox, are scaled to at
most ``video.max_width`` and encoded on its thread, and each access unit is serialized and handed to the SDK
from there. Without a client there is no subscription, no stream and no thread. A client that joins gets a
keyframe first (EncodeStream.request_keyframe); frames the encoder skipped or could not take are the channel's
drops.
"""
from __future__ import annotations

import threading
import time
from typing import Any, Callable

from components.foxglove_bridge.bridge_options import VideoOptions
from components.image_encoder.stream import EncodeStream, StreamCounts

IMAGE_TYPE = "sensor_msgs/msg/Image"
VIDEO_TYPE = "foxglove_msgs/msg/CompressedVideo"


def video_topic(image_topic: str) -> str:
    """The channel that offers ``image_topic`` as video (the ImageEncoder's output name)."""
    return f"{image_topic.rstrip('/')}/video"


class StampRateLimit:
    """Admits at most ``rate`` frames a second of the frames' own stamps (receive time for unstamped ones).

    Each admitted stamp is at least one period after the previous admission's due time, so any run of N
    admitted frames spans at least (N - 1) periods; a stamp that goes back (a bag played in a loop) restarts.
    """

    def __init__(self, rate: float) -> None:
        self._period_ns = int(1e9 / rate) if rate > 0 else 0
        self._due_ns: int | None = None

    def admit(self, stamp_ns: int) -> bool:
        if not self._period_ns:
            return True
        if not stamp_ns:
            stamp_ns = time.monotonic_ns()
        due, period = self._due_ns, self._period_ns
        if due is not None and due - period <= stamp_ns < due:
            return False
        on_time = due is not None and due <= stamp_ns < due + period
        self._due_ns = (due if on_time else stamp_ns) + period  # late by a period or more, or back: restart
        return True


class VideoFeed:
    """The intake of one video channel (module docstring): ChannelQueue's interface, and an encoder."""

    def __init__(self, source: str, options: VideoOptions, send: Callable[[Any], None],
                 log_error: Callable[[str], None]) -> None:
        self.source = source
        self._options = options
        self._send = send
        self._log_error = log_error
        self._lock = threading.Lock()
        self._stream: EncodeStream | None = None
        self._limit = StampRateLimit(options.max_rate)
        self._ended = StreamCounts()  # the counts of the streams that ended
        self.received = 0
        self.throttled = 0

    # --- the subscription's side (the publisher's thread, or the executor for frames over DDS) ---------------
    def offer(self, image: Any) -> None:
        """Hand ``image`` to the encoder if the rate limit admits it; never blocks."""
        stamp = image.header.stamp
        with self._lock:
            self.received += 1
            stream = self._stream
            if stream is None or not self._limit.admit(stamp.sec * 1_000_000_000 + stamp.nanosec):
                self.throttled += 1
                return
        stream.offer(image)

    # --- the bridge's side -----------------------------------------------------------------------------------
    def start(self) -> None:
        """The first client subscribed: start encoding (a new encoder begins with a keyframe)."""
        with self._lock:
            if self._stream is None:
                self._limit = StampRateLimit(self._options.max_rate)
                self._stream = EncodeStream(self.source, self._options.choice, self._options.max_width, self._send,
                                            self._log_error, width_at_most=True)

    def client_joined(self) -> None:
        """A client subscribed: its first message is a keyframe (SDK thread; the encoder may not run yet)."""
        with self._lock:
            stream = self._stream
        if stream is not None:
            stream.request_keyframe(skip_until_keyframe=True)

    def clear(self, timeout: float = 2.0) -> None:
        """The last client left (or the channel closes): stop encoding; the counts are kept."""
        with self._lock:
            stream, self._stream = self._stream, None
        if stream is not None:
            stream.stop(timeout)
            ended = stream.stats()
            for name in self._ended.__dict__:
                setattr(self._ended, name, getattr(self._ended, name) + ended[name])

    def take(self) -> None:
        """Nothing waits for the bridge's thread: the encoder's thread sends what it encodes."""
        return None

    def __len__(self) -> int:
        return 0

    # --- reporting -------------------------------------------------------------------------------------------
    def encoder_stats(self) -> dict[str, int]:
        """The encoder's counts over every stream (received, published, skipped, rejected, keyframes, bytes),
        ``running`` 1 while a stream encodes."""
        with self._lock:
            stream = self._stream
        current = stream.stats() if stream is not None else {}
        totals = {name: value + current.get(name, 0) for name, value in self._ended.__dict__.items()}
        return {**totals, "running": int(stream is not None)}

    @property
    def dropped(self) -> int:
        """Frames the encoder skipped (it was behind, or held them for a keyframe) or could not encode."""
        stats = self.encoder_stats()
        return stats["skipped"] + stats["rejected"]
