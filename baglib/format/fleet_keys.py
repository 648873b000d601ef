"""The ``custom_data`` keys of a fleet recording (rosbag2 metadata v9 ``custom_data``: a flat str -> str map).

``ipc-component record start`` loads one recorder per container and gives each bag these keys, so that every
bag of a session can be told apart and put back on one timeline by ``ipc-component bag merge``. Instants are
integers of nanoseconds since the epoch, written as decimal strings.
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
#: The container's clock minus the clock of the computer that ran ``record start`` (NTP-style estimate).
CLOCK_OFFSET_NS = "ipc.clock_offset_ns"
#: The offset measured again by ``record stop``, which the stop instant was corrected by (clocks drift).
STOP_CLOCK_OFFSET_NS = "ipc.stop_clock_offset_ns"
#: Half the round trip of the exchange the offset came from: the offset's error bound.
CLOCK_OFFSET_UNCERTAINTY_NS = "ipc.clock_offset_uncertainty_ns"

ALL = (SESSION, HOST, CONTAINER, START_NS, STOP_NS, CLOCK_OFFSET_NS, STOP_CLOCK_OFFSET_NS, CLOCK_OFFSET_UNCERTAINTY_NS)
