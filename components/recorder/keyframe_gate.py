"""Compressed video in a bag: every bag file's first message of a video topic is a keyframe, and no frame is lost.

A ``foxglove_msgs/CompressedVideo`` delta frame cannot be decoded without the frames before it, so a recording,
and each split file of it, must begin each video topic at a keyframe, or a player, ``ipc-component bag export``
or Foxglove opening that file shows nothing (or garbage) until the next keyframe.

**Which topics, which keyframes.** Every recorded CompressedVideo topic is gated; :class:`VideoTopics` learns it
when the recorder subscribes, before the first message can arrive. Where an ImageEncoder of this container
publishes it (the recorder's own, ``record.compress``, or any other; :mod:`components.image_encoder.outputs`), the
encoder's stream says which of its messages (by stamp) were keyframes, and can be asked for one. Any other
publisher's topic (another process, a user's component) is a *parsed* topic: FFmpeg's parser of its ``format``
says whether each access unit is a keyframe (components/image_encoder/access_units.py); its encoder cannot be asked
for one. A format FFmpeg has no parser for (or an access unit it cannot read) is recorded as it comes, with a
warning.

**The encoder's promise.** After a keyframe request returns, the next access unit the encoder publishes is a
keyframe (components/image_encoder/stream.py). The gate asks for one whenever a file or a topic begins. A parsed
topic has its keyframes when its publisher sends them (its keyframe interval): the delta frames before its first
one are dropped as ``awaiting_keyframe``, and a split waits for its keyframe as for the others, up to
:data:`SPLIT_HOLD`.

Rules:

* **A video topic begins at a keyframe.** At the start of a recording, and after a pause (:meth:`KeyframeGate.paused`:
  every message received from then on begins each video topic anew), the gate asks for keyframes; the recorder
  resumes and asks as one step, with the encoders' publication held (:meth:`VideoTopics.publication_held`), so no
  delta frame comes between. A delta frame that would still begin a topic in a file is dropped and counted as
  ``awaiting_keyframe``.
* **Each video topic splits at its own keyframe.** When a file is full (``storage.max_bagfile_size`` /
  ``_duration``) or a split is asked for (``~/split_bagfile``, ``record.split_at``), the encoders are asked for
  keyframes. Until a video topic's keyframe comes, its delta frames still go to the old file; its keyframe and
  what follows are held (in memory, bounded by the time below) for the new file. Once every video topic of the
  old file has its keyframe, the old file is closed and the held messages begin the new one. Other topics go to
  the old file until then. So no delta frame is dropped, with any number of cameras, and every file begins
  each of its video topics at a keyframe; split files of video topics overlap in time by up to a frame
  interval.
* The split waits at most :data:`SPLIT_HOLD` seconds (an encoder that stopped must not keep a file open for
  ever); a video topic whose keyframe did not come by then begins in the new file at its next keyframe, its
  delta frames until then counted as ``awaiting_keyframe``.
"""
from __future__ import annotations

import contextlib
import enum
import time
from collections.abc import Callable, Iterator
from typing import Any

from foxglove_msgs.msg import CompressedVideo
from rclpy.serialization import deserialize_message

from components.image_encoder import access_units, outputs

#: The message type of compressed video topics.
VIDEO_TYPE = "foxglove_msgs/msg/CompressedVideo"
#: The drop reason of a delta frame that would begin a video topic in a file (see the module docstring).
AWAITING_KEYFRAME = "awaiting_keyframe"
#: s: the longest a due split waits for the video topics' keyframes.
SPLIT_HOLD = 2.0


class VideoTopics:
    """The recorded video topics and how each one's keyframes are known (module docstring); thread-safe reads."""

    def __init__(self, container: Any, warn: Callable[[str], None] = lambda text: None) -> None:
        """``container``: the recorder's intra-process manager (None: not in-process, every topic is parsed);
        ``warn``: where a topic recorded as it comes is told, once per topic."""
        self._container = container
        self._warn = warn
        self._topics: frozenset[str] = frozenset()
        self._parsed: frozenset[str] = frozenset()  # topics of other publishers: keyframes read by FFmpeg's parser
        self._unread: set[str] = set()  # parsed topics already warned about (recorded as they come)
        self._due_ns: int | None = None  # a keyframe asked for from then on (record.start_at), also of later topics

    def add(self, topic: str) -> bool:
        """The recorder is about to subscribe to ``topic``: its files are begun at keyframes. True if an encoder
        of this container publishes it as video (it makes a new in-process reader's first message a keyframe:
        components/image_encoder/stream.py); False if another publisher does (a parsed topic)."""
        stream = outputs.stream_for(self._container, topic)
        self._topics = self._topics | {topic}
        if stream is None or not stream.is_video:
            self._parsed = self._parsed | {topic}
            return False
        due = self._due_ns
        if due is not None and due > time.time_ns():
            stream.request_keyframe(at_ns=due)
        return True

    @property
    def in_process(self) -> bool:
        """Whether this container's encoders can publish recorded topics (the recorder is intra-process)."""
        return self._container is not None

    def __contains__(self, topic: str) -> bool:
        return topic in self._topics

    def is_keyframe(self, topic: str, message: Any) -> bool:
        """Whether ``message`` (of the video topic ``topic``: a CompressedVideo object, or its serialized bytes as
        a subscription from another process gives them) is a keyframe: as its encoder published it, or as FFmpeg's
        parser reads it (True where it cannot: recorded as it comes)."""
        if topic in self._parsed:
            return self._parsed_keyframe(topic, message)
        stream = outputs.stream_for(self._container, topic)
        return stream is not None and stream.published_keyframe(message.timestamp)

    def _parsed_keyframe(self, topic: str, message: Any) -> bool:
        if isinstance(message, (bytes, bytearray, memoryview)):
            message = deserialize_message(bytes(message), CompressedVideo)
        try:
            return access_units.is_keyframe(message.format, message.data)
        except Exception as exc:  # noqa: BLE001 - an unknown format, or FFmpeg cannot read the unit
            if topic not in self._unread:
                self._unread.add(topic)
                self._warn(f"{topic}: which access units are keyframes cannot be read ({exc}): recorded as it "
                           "comes, so a file may begin with a frame that decodes only from the next keyframe")
            return True

    @contextlib.contextmanager
    def publication_held(self) -> Iterator[None]:
        """No encoder of a video topic publishes while inside (their publication locks, in topic order)."""
        with contextlib.ExitStack() as held:
            for topic in sorted(self._topics):
                stream = outputs.stream_for(self._container, topic)
                if stream is not None:
                    held.enter_context(stream.publication)
            yield

    def request_keyframes(self, at_ns: int | None = None) -> None:
        """Ask the encoder of every video topic for a keyframe: the next access unit each publishes is one (with
        ``at_ns``, the first one published from that wall-clock time on, also of a topic added before then)."""
        if at_ns is not None:
            self._due_ns = at_ns
        for topic in self._topics:
            stream = outputs.stream_for(self._container, topic)
            if stream is not None:  # an encoder unloaded meanwhile
                stream.request_keyframe(at_ns=at_ns)


class Verdict(enum.Enum):
    """What the writer does with a message (see :meth:`KeyframeGate.admit`)."""

    WRITE = "write"  # into the current file
    HOLD = "hold"    # keep it for the file that the pending split opens
    DROP = "drop"    # a delta frame that cannot begin its topic: counted as awaiting_keyframe


class KeyframeGate:
    """One bag's rules (module docstring). Used by its writer thread only, except :meth:`paused`, :meth:`begin`
    and :meth:`split`."""

    def __init__(self, video: VideoTopics) -> None:
        self.video = video
        self._started: set[str] = set()  # video topics that began (at a keyframe) in the current file
        self._split_asked = False
        self._split_since: float | None = None  # monotonic time the pending split began
        self._waiting: set[str] = set()  # during a split: video topics of the old file without their keyframe yet
        self._moved: set[str] = set()  # during a split: video topics whose keyframe is held for the new file
        self._restart_ns: int | None = None

    def begin(self, at_ns: int | None = None) -> None:
        """The recording (or this bag) starts taking messages, now or (``record.start_at``) at ``at_ns``: every
        video topic's first access unit from then on is a keyframe."""
        self.video.request_keyframes(at_ns)

    def paused(self) -> None:
        """The recording pauses: messages received from now on (after the resume) begin each video topic anew.
        Call :meth:`begin` once it resumes."""
        self._restart_ns = time.time_ns()

    def split(self) -> None:
        """A split is asked for (any thread): the keyframes are asked for now, and the split begins at the writer's
        next message."""
        self._split_asked = True
        self.video.request_keyframes()

    def admit(self, topic: str, message: Any, log_time_ns: int, full: bool) -> tuple[Verdict, bool]:
        """For the message about to be written: (what to do with it, does the pending split happen now, before
        it?). ``full``: the writer says the current file is full. On a split, the messages held so far begin the
        new file, before this one if it is written."""
        restart = self._restart_ns
        if restart is not None and log_time_ns >= restart:
            self._restart_ns = None
            self._started.clear()
        if self._split_since is None and (full or self._split_asked):
            if not self._split_asked:  # the file is full: the keyframes are asked for now
                self.video.request_keyframes()
            self._split_asked = False
            self._split_since = time.monotonic()
            self._waiting, self._moved = set(self._started), set()
        split = self._split_since is not None and (
            not self._waiting or time.monotonic() - self._split_since > SPLIT_HOLD)
        if split:
            self._end_split()
        # Whether a message is a keyframe is asked only where it decides (a parsed topic's costs a parse).
        video = topic in self.video
        if self._split_since is not None and video:
            if topic not in self._moved:
                if not self.video.is_keyframe(topic, message):
                    # the old file keeps a waiting topic until its keyframe; no other delta frame begins the new one
                    return (Verdict.WRITE if topic in self._waiting else Verdict.DROP), False
                self._waiting.discard(topic)
                self._moved.add(topic)
            if self._waiting:
                return Verdict.HOLD, False
            self._end_split()  # the last keyframe the split waited for: it begins the new file, held
            return Verdict.HOLD, True
        if self._split_since is not None or not video or topic in self._started:
            return Verdict.WRITE, split
        if self.video.is_keyframe(topic, message):
            self._started.add(topic)
            return Verdict.WRITE, split
        return Verdict.DROP, split

    def _end_split(self) -> None:
        """The old file closes: the topics whose keyframe is held have begun in the new one; those still waiting
        begin there at their next keyframe (asked for again)."""
        late = bool(self._waiting)
        self._started, self._moved, self._waiting = self._moved, set(), set()
        self._split_since = None
        if late:
            self.video.request_keyframes()
