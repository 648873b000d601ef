"""The ``custom_data`` keys of a fleet recording's bags, and the keys a merged bag keeps its inputs' under.

``ipc-component record start`` loads one recorder per container, each writing its own topics into
``<session>/<host>_<container>/``. Each of those bags says in its ``metadata.yaml`` ``custom_data`` (rosbag2
metadata v9: a flat string-to-string map) where and when it was recorded, so that ``bag merge`` can put them on
one timeline. All values are strings; instants are decimal integers of nanoseconds since the epoch.
"""
from __future__ import annotations

#: The session's name, the same in every bag of one recording.
SESSION = "ipc.session"
#: The host name of the computer whose container recorded the bag.
HOST = "ipc.host"
#: The full node name of the container that held the recorder.
CONTAINER = "ipc.container"
#: The scheduled start, on the clock of the computer that ran ``record start``.
START_NS = "ipc.start_ns"
#: The scheduled stop on that same clock; absent while none was scheduled.
STOP_NS = "ipc.stop_ns"
#: The container's clock minus the clock of the computer that ran ``record start`` (NTP-style estimate): a time
#: ``t`` of this bag is ``t - offset`` on that computer's clock.
CLOCK_OFFSET_NS = "ipc.clock_offset_ns"
#: The offset measured again by ``record stop``, which the stop instant was corrected by (clocks drift).
STOP_CLOCK_OFFSET_NS = "ipc.stop_clock_offset_ns"
#: Half the round trip of the exchange the offset came from: the offset's error bound.
CLOCK_OFFSET_UNCERTAINTY_NS = "ipc.clock_offset_uncertainty_ns"

#: A merged bag keeps input ``n``'s ``custom_data`` key ``k`` as ``input.<n>.k`` (see :func:`input_key`).
INPUT_PREFIX = "input"


def input_key(index: int, key: str) -> str:
    """``input.<index>.<key>``: where a merged bag keeps input ``index``'s ``key`` (``path``, ``shift_ns``, or a
    ``custom_data`` key of the input)."""
    return f"{INPUT_PREFIX}.{index}.{key}"
