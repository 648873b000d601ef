"""Tests of components.frame_buffers: a frame buffer is handed out again only when nobody else holds it."""
from __future__ import annotations

from array import array
from typing import Any, Callable

import numpy as np
import pytest
from sensor_msgs.msg import Image

from components.frame_buffers import FrameBuffers


def filler(size: int = 64) -> Callable[[int], array]:
    return lambda slot: array("B", bytes([slot]) * size)


def message_over(buffer: array) -> Image:
    """An Image that keeps ``buffer`` itself, as the drivers build it (the constructor would copy it)."""
    msg = Image(check_fields=True)
    msg.data = buffer
    assert msg.data is buffer
    return msg


def test_a_buffer_nobody_holds_is_handed_out_again() -> None:
    frames = FrameBuffers(3, filler())
    first = id(frames.take(0))
    assert [id(frames.take(sequence)) == first for sequence in (3, 6, 9)] == [True, True, True]
    assert (frames.filled, frames.reused) == (1, 3)
    assert id(frames.take(1)) != first and frames.filled == 2, "another slot shares the buffer"


@pytest.mark.parametrize("hold", [
    lambda buffer: buffer,
    lambda buffer: memoryview(buffer)[8:16],
    lambda buffer: np.frombuffer(buffer, dtype=np.uint8),
    lambda buffer: [buffer],
    message_over,
], ids=["buffer", "memoryview", "numpy", "list", "message"])
def test_a_held_buffer_is_never_handed_out_again(hold: Callable[[array], Any]) -> None:
    frames = FrameBuffers(2, filler())
    held = hold(frames.take(0))
    taken = frames.take(2)
    assert taken is not (held if isinstance(held, array) else None)
    taken[0:8] = array("B", range(8))  # what a driver writes into the buffer it took
    if isinstance(held, Image):
        assert held.data.tobytes() == bytes(64), "the held message's data changed"
    else:
        assert bytes(memoryview(held[0] if isinstance(held, list) else held).cast("B"))[:8] == bytes(8)
    assert frames.reused == 0 and frames.filled == 2


def test_clear_drops_the_buffers_but_not_held_frames() -> None:
    frames = FrameBuffers(2, filler())
    held = frames.take(0)
    frames.take(1)
    frames.clear()
    assert frames._buffers == [None, None] and held.tobytes() == bytes(64)
    assert frames.take(2) is not held and frames.filled == 3


def test_at_least_two_slots() -> None:
    with pytest.raises(ValueError, match="at least 2 slots"):
        FrameBuffers(1, filler())
