"""The encoders' outputs as in-process readers see them: which stream publishes a topic.

A recorder in the same container as an ImageEncoder must know, before the first message of ``<image>/video`` can
reach it, that the topic carries video, which of its messages are keyframes (``foxglove_msgs/CompressedVideo``
has no flag for it, and no bitstream is parsed here: the stream remembers the stamps of the keyframes it
published, :meth:`~components.image_encoder.stream.EncodeStream.published_keyframe`), whom to ask for a keyframe
(a split, a resume), and what the encoder did with the raw frames (a bag accounts for the frames the encoder
lost). :func:`stream_for` answers with the :class:`~components.image_encoder.stream.EncodeStream` that publishes
an output topic in a container (keyed by the container's intra-process manager, so a recorder never sees another
container's encoder). An encoder registers each stream before it creates the stream's publisher, so a topic that
is on the graph is already known here.
"""
from __future__ import annotations

import threading
import weakref
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from components.image_encoder.stream import EncodeStream

_lock = threading.Lock()
_streams: weakref.WeakKeyDictionary[Any, dict[str, EncodeStream]] = weakref.WeakKeyDictionary()


def register(container: Any, topic: str, stream: EncodeStream) -> None:
    """``stream`` publishes ``topic`` in the container whose intra-process manager is ``container`` (None: an
    encoder without intra-process comms, which no in-process reader sees)."""
    if container is None:
        return
    with _lock:
        _streams.setdefault(container, {})[topic] = stream


def unregister(container: Any, topic: str, stream: EncodeStream) -> None:
    if container is None:
        return
    with _lock:
        streams = _streams.get(container, {})
        if streams.get(topic) is stream:
            del streams[topic]


def stream_for(container: Any, topic: str) -> EncodeStream | None:
    """The encoder stream that publishes ``topic`` in that container, if an encoder there does."""
    if container is None:
        return None
    with _lock:
        return _streams.get(container, {}).get(topic)
