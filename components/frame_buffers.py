"""Frame buffers a simulated driver takes back once nobody references them any more.

Why: building a frame was one memcpy of the whole frame into a fresh buffer for every publish (6.2 MB per
1080p rgb8 image, 373 MB/s for the S1 rig's two cameras), the largest single cost of the drivers. A real
camera does not pay it: its DMA engine fills a small ring of buffers that the driver hands out and gets back.
:class:`FrameBuffers` is that ring. Slot ``sequence % slots`` holds the buffer of every frame with that
sequence remainder, filled once by ``fill(slot)``; it is handed out again only when the slot is its only
holder, so a message that is still queued, cached by the recorder or kept by a subscriber never sees its bytes
change. Otherwise the slot gets a freshly filled buffer and the old one stays with whoever holds it.

Content is therefore a function of the sequence number alone, provided the driver writes into a handed-out
buffer only bytes it rewrites on every take (the sequence number in the first 8 bytes): tests rebuild any
published frame from its sequence number, whether its buffer was reused or not.

"Only holder" is CPython's reference count, read under the GIL on the thread that publishes. Every way of
keeping a buffer — the message, a ``memoryview`` or numpy array over it, a copy of the list that holds it —
holds a reference, so it counts; a ``weakref`` does not, and must not be used to keep a frame.
"""
from __future__ import annotations

import sys
from array import array
from typing import Callable

from component_container.component_node import REUSE_WATCH

#: Slots of a driver's ring. The container's intra-process publisher remembers a publisher's last
#: ``REUSE_WATCH`` messages (see ``component_node``) and forgets one only at a later publish: with one slot
#: more than that, the buffer a frame gets is never one the publisher still remembers; and by then, three
#: frame periods later, the recorder (which writes within tens of milliseconds) has normally released it too.
FRAME_SLOTS = REUSE_WATCH + 1
#: References to a buffer that only its slot holds, as :meth:`FrameBuffers.take` counts them: the slot list,
#: the local name, and ``sys.getrefcount``'s own argument.
_REFS_WHEN_FREE = 3


class FrameBuffers:
    """``slots`` reusable frame buffers; see the module docstring."""

    def __init__(self, slots: int, fill: Callable[[int], array]) -> None:
        if slots < 2:
            raise ValueError(f"FrameBuffers needs at least 2 slots (consecutive frames must differ), got {slots}")
        self._fill = fill
        self._buffers: list[array | None] = [None] * slots
        #: Buffers handed out again without filling, and buffers filled (a slot's first use, or its buffer was
        #: still held by someone): the tests read them.
        self.reused = 0
        self.filled = 0

    def clear(self) -> None:
        """Drop the ring's buffers (a driver being destroyed): a node lives on until the garbage collector
        finds its reference cycles, and its frames should not live on with it."""
        self._buffers = [None] * len(self._buffers)

    def take(self, sequence: int) -> array:
        """The buffer for frame ``sequence``: ``fill(sequence % slots)``, apart from the bytes the caller writes
        on every take."""
        slot = sequence % len(self._buffers)
        buffer = self._buffers[slot]
        if buffer is not None and sys.getrefcount(buffer) == _REFS_WHEN_FREE:
            self.reused += 1
            return buffer
        buffer = self._buffers[slot] = self._fill(slot)
        self.filled += 1
        return buffer
