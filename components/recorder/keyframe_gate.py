"""Compressed video in a bag: every bag file's first message of a video topic is a keyframe.

A ``foxglove_msgs/CompressedVideo`` delta frame cannot be decoded without the frames before it, so a recording,
and each split file of it, must begin each video topic at a keyframe, or a player, ``ipc-component bag export``
or Foxglove opening that file shows nothing (or garbage) until the next keyframe, up to a keyframe interval
later. Two rules keep every file decodable on its own:

* **A split waits for a keyframe.** When a file is full (``storage.max_bagfile_size`` / ``_duration``) or a split
  is asked for (``~/split_bagfile``, ``record.split_at``), the encoder is asked for a keyframe at that moment and
  the file is closed just before the first keyframe of a video topic that it holds arrives; everything until
  then still goes to the old file. Holding the split instead of dropping frames loses nothing: with one camera,
  every frame is in exactly one file and each file starts with a keyframe. The split is held at most
  :data:`SPLIT_HOLD` seconds (an encoder that stopped must not keep a file open for ever).
* **A video topic begins at a keyframe.** In a new file (the recording's first, a file after a split, the
  recording resumed after a pause) a video topic's delta frames are dropped until its first keyframe, and
  counted as ``awaiting_keyframe`` in ``drop_reasons``. The encoder is asked for a keyframe whenever this can
  happen (start, split, resume), so this is at most the few frames it already had in hand; with several cameras,
  the ones whose keyframe came after the one that closed the file lose those frames.

Which messages are keyframes: CompressedVideo has no flag for it and no bitstream is parsed here; the encoder the
recorder loaded reports the stamp of each keyframe it publishes (:class:`KeyframeLog`), before the message
reaches the recorder.
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Any, Callable

#: The drop reason of a delta frame that would begin a video topic in a file (see the module docstring).
AWAITING_KEYFRAME = "awaiting_keyframe"
#: s: the longest a due split waits for a video keyframe.
SPLIT_HOLD = 2.0
#: Keyframe stamps remembered per topic (a keyframe the recorder never writes, e.g. dropped, is forgotten).
STAMPS_KEPT = 64


def _stamp(message: Any) -> tuple[int, int]:
    return message.timestamp.sec, message.timestamp.nanosec


class KeyframeLog:
    """The recorded video topics, and the stamps of the keyframes the encoder published on them (thread-safe)."""

    def __init__(self, request_keyframe: Callable[[], Any]) -> None:
        self.request_keyframe = request_keyframe
        self._lock = threading.Lock()
        self._stamps: dict[str, collections.deque[tuple[int, int]]] = {}

    def add_topic(self, topic: str) -> None:
        """``topic`` carries video: the gates keep its files decodable."""
        with self._lock:
            self._stamps.setdefault(topic, collections.deque(maxlen=STAMPS_KEPT))

    def is_video(self, topic: str) -> bool:
        return topic in self._stamps

    def published(self, topic: str, message: Any) -> None:
        """The encoder's keyframe listener: ``message`` on ``topic`` is a keyframe."""
        with self._lock:
            stamps = self._stamps.get(topic)
            if stamps is not None:
                stamps.append(_stamp(message))

    def is_keyframe(self, topic: str, message: Any) -> bool:
        """Whether ``message`` (a CompressedVideo object) is a keyframe the encoder reported."""
        stamp = _stamp(message)
        with self._lock:
            stamps = self._stamps[topic]
            if stamp in stamps:
                stamps.remove(stamp)
                return True
        return False


class KeyframeGate:
    """One bag's rules (module docstring). Used by its writer thread only, except :meth:`restart` / :meth:`split`.
    """

    def __init__(self, log: KeyframeLog) -> None:
        self.log = log
        self._started: set[str] = set()  # video topics that began (at a keyframe) in the current file
        self._split_since: float | None = None  # monotonic time the pending split became due
        self._split_asked = False
        self._restart_ns: int | None = None
        log.request_keyframe()

    def restart(self) -> None:
        """The recording resumes (after a pause): messages received from now begin each video topic anew."""
        self._restart_ns = time.time_ns()
        self.log.request_keyframe()

    def split(self) -> None:
        """A split is asked for (any thread): it happens at the writer's next chance (see :meth:`splits_before`)."""
        self._split_asked = True

    def splits_before(self, topic: str, message: Any, log_time_ns: int, full: bool) -> tuple[bool, bool]:
        """For the message about to be written: (close the file before it?, write it?). ``full``: the writer
        says the file is full. A message not written is counted as ``awaiting_keyframe`` by the caller."""
        restart = self._restart_ns
        if restart is not None and log_time_ns >= restart:
            self._restart_ns = None
            self._started.clear()
        video = self.log.is_video(topic)
        keyframe = video and self.log.is_keyframe(topic, message)
        split = False
        if full or self._split_asked:
            if self._split_since is None:
                self._split_since = time.monotonic()
                self.log.request_keyframe()
            split = (not self._started or (keyframe and topic in self._started)
                     or time.monotonic() - self._split_since > SPLIT_HOLD)
            if split:
                self._started.clear()
                self._split_since, self._split_asked = None, False
        if not video or topic in self._started:
            return split, True
        if keyframe:
            self._started.add(topic)
        return split, keyframe
