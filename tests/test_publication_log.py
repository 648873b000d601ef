"""A container tells its own DDS samples from foreign ones by the writer's sequence number and the source time
window of the write (component_container.intra_process.LocalPublicationLog). A reader of the same process can
take a sample while the write is still in progress (another executor thread): the sample must already be known
as local then, or an in-process subscriber gets the message twice (once in-process, once over DDS)."""
from __future__ import annotations

import time

import pytest

from component_container.intra_process import LocalPublicationLog


def test_a_sample_taken_during_its_write_is_known_as_local() -> None:
    log = LocalPublicationLog(depth=4)
    seen_during: list[bool] = []
    log.record(lambda: seen_during.append(log.contains(1, time.time_ns())))
    log.record(lambda: seen_during.append(log.contains(2, time.time_ns())))
    assert seen_during == [True, True]


def test_closed_windows_match_only_their_own_write() -> None:
    log = LocalPublicationLog(depth=4)
    inside: list[int] = []
    log.record(lambda: inside.append(time.time_ns()))
    assert log.contains(1, inside[0])
    assert not log.contains(1, time.time_ns() + 1_000_000_000)  # a later sample with that number: not this write
    assert not log.contains(1, inside[0] - 1_000_000_000)
    assert not log.contains(2, inside[0])                       # a number this publisher has not used yet


def test_a_failed_write_leaves_no_entry_and_keeps_the_numbering() -> None:
    log = LocalPublicationLog(depth=4)

    def refused() -> None:
        raise RuntimeError("the middleware refused the write")

    with pytest.raises(RuntimeError):
        log.record(refused)
    assert not log.contains(1, time.time_ns())
    inside: list[int] = []
    log.record(lambda: inside.append(time.time_ns()))
    assert log.contains(1, inside[0])  # the first write that happened is number 1, as DDS numbers it


def test_old_writes_are_forgotten_beyond_the_depth() -> None:
    log = LocalPublicationLog(depth=0)  # the log keeps at least its minimum depth
    times: list[int] = []
    for _ in range(2000):
        log.record(lambda: times.append(time.time_ns()))
    assert log.contains(2000, times[-1])
    assert not log.contains(1, times[0])
