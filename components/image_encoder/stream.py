"""One camera's encoding: a worker thread fed by a mailbox of at most :data:`QUEUE_FRAMES` frames.

The subscription hands each ``sensor_msgs/Image`` to :meth:`EncodeStream.offer`, which only appends a reference
under a lock and wakes the worker: it never blocks and never waits for the codec, so a driver that delivers
in-process (inline, in its own ``publish()``) is never slowed by the encoder. When the mailbox is full the oldest
frame waiting is skipped and counted: a slow encoder loses frames, it never queues them without bound.

Ownership (docs/intra-process.md): a published message belongs to its subscribers and is never mutated, so the
worker keeps the message itself and reads its pixels through a numpy view of its own buffer, no copy. A driver
that reuses frame buffers (components/frame_buffers.py) sees the reference and fills a fresh buffer instead.

A viewer that joins a running stream (the Foxglove bridge's video channels) asks for a keyframe with
``skip_until_keyframe``: the access units that come out before it (the frame the worker was encoding) are
skipped and counted, so the newcomer's first message is the keyframe. The viewers already watching lose only
that frame, which nothing after the keyframe refers to.
"""
from __future__ import annotations

import collections
import threading
from array import array
from dataclasses import dataclass
from typing import Any, Callable

from builtin_interfaces.msg import Time
from foxglove_msgs.msg import CompressedVideo
from sensor_msgs.msg import CompressedImage

from components.image_encoder.codecs import CodecChoice, StillCodec, VideoCodec, pixels_of, scaled_size

#: Frames a stream holds while its encoder is busy: one being waited for, one more to absorb jitter.
QUEUE_FRAMES = 2


@dataclass
class StreamCounts:
    """What one stream did with the frames it was offered (each frame ends in exactly one of the last four)."""

    received: int = 0
    published: int = 0
    skipped: int = 0    # the encoder was behind (dropped from the full mailbox), or held for a keyframe
    rejected: int = 0   # the frame could not be encoded (its encoding, its size), or the encoder failed
    keyframes: int = 0
    bytes: int = 0

    def as_dict(self, waiting: int) -> dict[str, int]:
        """The counts, and ``waiting``: frames received and not yet done (in the mailbox or being encoded)."""
        return {**self.__dict__, "waiting": waiting}


class EncodeStream:
    """Encodes the images of one topic on a thread of its own and publishes each result with
    ``publish(message, keyframe)`` (``keyframe``: a picture that decodes on its own; every still is one)."""

    def __init__(self, topic: str, choice: CodecChoice, out_width: int, publish: Callable[[Any, bool], None],
                 log_error: Callable[[str], None], *, subscribers: Callable[[], int] | None = None,
                 width_at_most: bool = False) -> None:
        """``subscribers``: the readers of the output, a keyframe when they grow (None: keyframes on request
        only); ``width_at_most``: ``out_width`` is a maximum, never an upscale (scaled_size)."""
        self.topic = topic
        self._choice = choice
        self._out_width = out_width
        self._width_at_most = width_at_most
        self._publish = publish
        self._subscribers = subscribers
        self._log_error = log_error
        self._still = None if choice.is_video else StillCodec(choice, out_width)
        self._video: VideoCodec | None = None
        self._stamps: dict[int, tuple[Time, str]] = {}
        self._known_subscribers = 0
        self._queue: collections.deque[Any] = collections.deque()
        self._wake = threading.Condition()
        self._keyframe_requested = False
        self._skip_until_keyframe = False
        self._in_hand = 0  # 1 while the worker encodes a frame it took from the mailbox
        self._stopping = False
        self._reported: set[str] = set()
        self.counts = StreamCounts()
        self._thread = threading.Thread(target=self._run, name=f"encode:{topic}", daemon=True)
        self._thread.start()

    # --- the subscriber's side (any thread; never blocks) ----------------------------------------------------
    def offer(self, image: Any) -> None:
        """Queue ``image`` for encoding; skip (and count) the oldest waiting frame if the mailbox is full."""
        with self._wake:
            self.counts.received += 1
            if len(self._queue) >= QUEUE_FRAMES:
                self._queue.popleft()
                self.counts.skipped += 1
            self._queue.append(image)
            self._wake.notify()

    def request_keyframe(self, skip_until_keyframe: bool = False) -> None:
        """Make the next encoded frame a keyframe with parameter sets (a recording, split or viewer starts);
        with ``skip_until_keyframe``, nothing else is published before it (module docstring)."""
        with self._wake:
            self._keyframe_requested = True
            self._skip_until_keyframe = self._skip_until_keyframe or skip_until_keyframe

    def stats(self) -> dict[str, int]:
        with self._wake:
            return self.counts.as_dict(len(self._queue) + self._in_hand)

    def stop(self, timeout: float) -> None:
        """Stop the worker (it finishes the frame in hand); the frames still waiting are counted as skipped."""
        with self._wake:
            self._stopping = True
            self._wake.notify()
        self._thread.join(timeout)
        with self._wake:
            self.counts.skipped += len(self._queue)
            self._queue.clear()

    # --- the worker ------------------------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._wake:
                while not self._queue and not self._stopping:
                    self._wake.wait()
                if self._stopping:
                    return
                image = self._queue.popleft()
                keyframe, self._keyframe_requested = self._keyframe_requested, False
                self._in_hand = 1
            try:
                self._encode(image, keyframe)
            except Exception as exc:  # a frame it cannot take, or the codec failed: counted, the stream goes on
                with self._wake:
                    self.counts.rejected += 1
                self._video = None  # the next frame opens a fresh encoder, starting with a keyframe
                self._report(str(exc))
            finally:
                with self._wake:
                    self._in_hand = 0

    def _report(self, text: str) -> None:
        """Log each distinct problem once (a camera of odd width would otherwise log 30 lines a second)."""
        if text not in self._reported:
            self._reported.add(text)
            self._log_error(f"Cannot encode an image of {self.topic}: {text} (such frames are counted as rejected)")

    def _encode(self, image: Any, keyframe: bool) -> None:
        if self._still is not None:
            data = self._still.encode(image)
            message = CompressedImage(check_fields=True)
            message.header = image.header
            message.format = self._still.format_of(image.encoding)
            self._send(message, data, True)
            return
        pixels = pixels_of(image)
        size = scaled_size(image.width, image.height, self._out_width, even=True, at_most=self._width_at_most)
        if self._video is None or self._video.size != size:
            self._video = VideoCodec(self._choice, *size)  # a new encoder starts with a keyframe
            self._stamps.clear()
        if self._subscribers is not None:
            subscribers = self._subscribers()
            if subscribers > self._known_subscribers:
                keyframe = True  # a new subscriber (a viewer, a recorder) starts decodable
            self._known_subscribers = subscribers
        self._stamps[self._video.next_pts] = (image.header.stamp, image.header.frame_id)
        for pts, is_keyframe, data in self._video.encode(pixels, image.encoding, keyframe):
            if not data:
                continue
            stamp, frame_id = self._stamps.pop(pts, (image.header.stamp, image.header.frame_id))
            message = CompressedVideo(check_fields=True)
            message.timestamp, message.frame_id, message.format = stamp, frame_id, self._choice.video_format
            self._send(message, data, is_keyframe)

    def _send(self, message: Any, data: bytes, keyframe: bool) -> None:
        with self._wake:
            if self._skip_until_keyframe and not keyframe:
                self.counts.skipped += 1
                return
            self._skip_until_keyframe = False
        buffer = array("B")
        buffer.frombytes(data)
        message.data = buffer  # check_fields=True keeps the array as it is (no second copy)
        self._publish(message, keyframe)
        with self._wake:
            self.counts.published += 1
            self.counts.keyframes += keyframe
            self.counts.bytes += len(data)
