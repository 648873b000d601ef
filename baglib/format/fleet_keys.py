"""The ``custom_data`` keys of a fleet recording's bags, and the keys a merged bag keeps its inputs' under.

A fleet recording runs one recorder per computer (container), each writing its own topics into
``<session>/<host>_<container>/``. Each of those bags says in its ``metadata.yaml`` ``custom_data`` (a flat
string-to-string map in rosbag2) where and when it was recorded, so that ``bag merge`` can put them on one
timeline. All values are strings; times are decimal integers of nanoseconds.
"""
from __future__ import annotations

__all__ = [
    "CLOCK_OFFSET_NS", "CLOCK_OFFSET_UNCERTAINTY_NS", "CONTAINER", "HOST", "INPUT_PREFIX", "SESSION", "START_NS",
    "STOP_NS", "input_key",
]

#: The recording session all bags of one fleet recording share.
SESSION = "ipc.session"
#: The computer the recorder ran on.
HOST = "ipc.host"
#: The container (process) on that computer the recorder was loaded into.
CONTAINER = "ipc.container"
#: The scheduled start, epoch nanoseconds.
START_NS = "ipc.start_ns"
#: The scheduled stop, epoch nanoseconds, or ``""`` when none was scheduled.
STOP_NS = "ipc.stop_ns"
#: The container's clock minus the commanding host's clock, NTP-style: a time ``t`` of this bag is
#: ``t - offset`` on the commanding host's clock.
CLOCK_OFFSET_NS = "ipc.clock_offset_ns"
#: How far ``ipc.clock_offset_ns`` may be off (half the round trip it was measured with).
CLOCK_OFFSET_UNCERTAINTY_NS = "ipc.clock_offset_uncertainty_ns"

#: A merged bag keeps input ``n``'s ``custom_data`` key ``k`` as ``input.<n>.k`` (see :func:`input_key`).
INPUT_PREFIX = "input"


def input_key(index: int, key: str) -> str:
    """``input.<index>.<key>``: where a merged bag keeps input ``index``'s ``key`` (``path``, ``shift_ns``, or a
    ``custom_data`` key of the input)."""
    return f"{INPUT_PREFIX}.{index}.{key}"
