"""One camera's encoding: a worker thread fed by a mailbox of at most :data:`QUEUE_FRAMES` frames.

The subscription hands each ``sensor_msgs/Image`` to :meth:`EncodeStream.offer`, which only appends a reference
under a lock and wakes the worker: it never blocks and never waits for the codec, so a driver that delivers
in-process (inline, in its own ``publish()``) is never slowed by the encoder. When the mailbox is full the oldest
frame waiting is skipped and counted: a slow encoder loses frames, it never queues them without bound. An input
filter (:meth:`EncodeStream.set_input_filter`: a recorder's ``record.max_rates``) may leave frames out before
they are queued; they are counted as ``rate_limited``.

**A keyframe request is met by the next access unit published.** The frame the worker is encoding when a
keyframe is asked for (a recording starts, splits or resumes; a new reader subscribes) would come out as a delta
frame after the request: the worker then encodes that same picture again as a keyframe and publishes only that
one. Publishing and requesting hold one lock, so every access unit published after :meth:`request_keyframe`
returned, and the first one any reader that subscribed in-process gets, is a keyframe: a file or a reader that
starts there loses no frame and decodes from its first message.

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
import time
from array import array
from dataclasses import dataclass
from typing import Any, Callable

from builtin_interfaces.msg import Time
from foxglove_msgs.msg import CompressedVideo
from sensor_msgs.msg import CompressedImage

from components.image_encoder.codecs import CodecChoice, StillCodec, VideoCodec, pixels_of, scaled_size

#: Frames a stream holds while its encoder is busy: one being waited for, one more to absorb jitter.
QUEUE_FRAMES = 2
#: Keyframe stamps remembered (published_keyframe): far more than the keyframes in flight to a reader.
KEYFRAME_STAMPS_KEPT = 64


@dataclass
class StreamCounts:
    """What one stream did with the frames it was offered: each frame received ends in exactly one of published,
    skipped, rejected, stopped and rate_limited, or is still ``waiting``."""

    received: int = 0
    published: int = 0
    skipped: int = 0    # the encoder was behind (dropped from the full mailbox), or held for a keyframe
    rejected: int = 0   # the frame could not be encoded (its encoding, its size), or the encoder failed
    stopped: int = 0    # still waiting when the stream stopped (the encoder was unloaded)
    rate_limited: int = 0  # left out by the input filter before the mailbox, by design
    keyframes: int = 0
    bytes: int = 0

    def as_dict(self, waiting: int) -> dict[str, int]:
        """The counts, and ``waiting``: frames received and not yet done (in the mailbox or being encoded)."""
        return {**self.__dict__, "waiting": waiting}


class EncodeStream:
    """Encodes the images of one topic on a thread of its own and publishes each result with
    ``publish(message, keyframe)`` (``keyframe``: a picture that decodes on its own; every still is one)."""

    def __init__(self, topic: str, choice: CodecChoice, out_width: int, publish: Callable[[Any, bool], None],
                 log_error: Callable[[str], None], *, subscribers: Callable[[], tuple[int, ...]] | None = None,
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
        self._known_subscribers: tuple[int, ...] = ()
        self._queue: collections.deque[Any] = collections.deque()
        self._wake = threading.Condition()
        self._keyframe_requested = False
        self._keyframe_at_ns: int | None = None  # a keyframe asked for from that wall-clock time on
        self._skip_until_keyframe = False
        # Held while an access unit is published or a keyframe is requested (module docstring); never while
        # encoding, and never by offer(), so a driver's publish() does not wait for it.
        self._publish_lock = threading.RLock()  # a reader that asks for a keyframe inline, in publish()
        self._input_filter: Callable[[], bool] | None = None
        # Stamps of the last keyframes published: CompressedVideo has no keyframe flag (published_keyframe)
        self._keyframe_stamps: collections.deque[tuple[int, int]] = collections.deque(maxlen=KEYFRAME_STAMPS_KEPT)
        self._in_hand = 0  # 1 while the worker encodes a frame it took from the mailbox
        self._stopping = False
        self._reported: set[str] = set()
        self.counts = StreamCounts()
        self._thread = threading.Thread(target=self._run, name=f"encode:{topic}", daemon=True)
        self._thread.start()

    # --- the subscriber's side (any thread; never blocks) ----------------------------------------------------
    def offer(self, image: Any) -> None:
        """Queue ``image`` for encoding; skip (and count) the oldest waiting frame if the mailbox is full."""
        admit = self._input_filter
        with self._wake:
            self.counts.received += 1
            if admit is not None and not admit():
                self.counts.rate_limited += 1
                return
            if len(self._queue) >= QUEUE_FRAMES:
                self._queue.popleft()
                self.counts.skipped += 1
            self._queue.append(image)
            self._wake.notify()

    def request_keyframe(self, skip_until_keyframe: bool = False, at_ns: int | None = None) -> None:
        """Make the next access unit published a keyframe with parameter sets (a recording, split or viewer
        starts; module docstring); with ``at_ns`` (wall clock, ns), the first one published at or after that time
        (a recording window that opens then). With ``skip_until_keyframe``, nothing else is published before it
        (a viewer whose subscription began before this call)."""
        with self._publish_lock, self._wake:
            if at_ns is None:
                self._keyframe_requested = True
            else:
                self._keyframe_at_ns = at_ns if self._keyframe_at_ns is None else min(at_ns, self._keyframe_at_ns)
            self._skip_until_keyframe = self._skip_until_keyframe or skip_until_keyframe

    def set_input_filter(self, admit: Callable[[], bool] | None) -> None:
        """``admit()`` decides, for each frame offered, whether it is encoded (False: counted as rate_limited);
        called in the publisher's thread, so it must be quick and thread-safe."""
        self._input_filter = admit

    @property
    def is_video(self) -> bool:
        return self._choice.is_video

    @property
    def publication(self) -> threading.RLock:
        """Held while an access unit is published: a reader that holds it knows nothing is published meanwhile
        (a recorder resumes and asks for a keyframe as one step)."""
        return self._publish_lock

    def published_keyframe(self, stamp: Any) -> bool:
        """Whether the video access unit stamped ``stamp`` (a ``builtin_interfaces/Time``) that this stream
        published is a keyframe: an in-process reader's question, since CompressedVideo has no flag for it."""
        with self._wake:  # a deque may not change while it is searched
            return (stamp.sec, stamp.nanosec) in self._keyframe_stamps

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
            self.counts.stopped += len(self._queue)
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
                self._in_hand = 1
            try:
                self._encode(image)
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

    def _encode(self, image: Any) -> None:
        if self._still is not None:
            data = self._still.encode(image)
            message = CompressedImage(check_fields=True)
            message.header = image.header
            message.format = self._still.format_of(image.encoding)
            self._send(message, data, True)  # every still is a keyframe
            return
        pixels = pixels_of(image)
        size = scaled_size(image.width, image.height, self._out_width, even=True, at_most=self._width_at_most)
        if self._video is None or self._video.size != size:
            self._video = VideoCodec(self._choice, *size)  # a new encoder starts with a keyframe
            self._stamps.clear()
        keyframe = self._take_keyframe_request()
        while True:
            self._stamps[self._video.next_pts] = (image.header.stamp, image.header.frame_id)
            units = self._video.encode(pixels, image.encoding, keyframe)
            with self._publish_lock:
                if units and self._keyframe_due(units):
                    keyframe = True  # asked for while encoding: this picture again, as a keyframe
                    for pts, _, _ in units:  # the units not published leave no stamp behind
                        self._stamps.pop(pts, None)
                    continue
                for pts, is_keyframe, data in units:
                    if not data:
                        continue
                    stamp, frame_id = self._stamps.pop(pts, (image.header.stamp, image.header.frame_id))
                    message = CompressedVideo(check_fields=True)
                    message.timestamp, message.frame_id, message.format = stamp, frame_id, self._choice.video_format
                    if is_keyframe:
                        with self._wake:
                            self._keyframe_stamps.append((stamp.sec, stamp.nanosec))
                    self._send(message, data, is_keyframe)
                return

    def _take_keyframe_request(self) -> bool:
        """Whether a keyframe is asked for now (since the last one was published, or from a time that has come);
        the request is taken."""
        with self._wake:
            requested, self._keyframe_requested = self._keyframe_requested, False
            if self._keyframe_at_ns is not None and time.time_ns() >= self._keyframe_at_ns:
                requested, self._keyframe_at_ns = True, None
        return requested

    def _keyframe_due(self, units: list[tuple[int, bool, bytes]]) -> bool:
        """With the publish lock held, about to publish ``units``: must they be a keyframe instead? Yes if a
        keyframe was asked for meanwhile, or a reader subscribed since the last publish (it must begin at a
        keyframe). A keyframe among them meets either."""
        newcomer = False
        if self._subscribers is not None:
            counts = self._subscribers()
            newcomer = any(now > before for now, before in zip(counts, self._known_subscribers or (0,) * len(counts)))
            self._known_subscribers = counts
        if any(is_keyframe and data for _, is_keyframe, data in units):
            self._take_keyframe_request()
            return False
        return self._take_keyframe_request() | newcomer

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
