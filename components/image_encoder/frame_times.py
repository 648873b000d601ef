"""The times of an exported video's frames: as close to the recorded stamps as the stream's own frame rate allows.

Camera stamps are not always a frame interval apart: a driver that catches up after a stall publishes a burst of
frames 1.4 ms apart, each stamped when it was built. Stored as they are, such frames are legal in an MP4 but not
what players and FFmpeg expect: ``ffmpeg -i x.mp4 -f null -`` (and every output that keeps the frames' times)
times its output at the rate it guesses for the stream (about the camera's), so two frames closer than one of its
ticks get the same time, and it warns "non monotonically increasing dts" for each.

Here each frame is at least one *local frame interval* after the frame before (the lower quartile of the stamp
intervals around it: the camera's period, not the bursts'), and otherwise as close to its stamp as possible: the
times are the least-squares fit of the stamps under those spacings (a monotone regression, solved by pooling
adjacent violators). A burst spreads into the gap before it, which is where its frames were due; the frames
around it move by what the fit spreads over them (a few milliseconds in a stream of some seconds). A regular
stream, or one whose rate changes, keeps its stamps exactly. Frames are never reordered or dropped.
"""
from __future__ import annotations

from collections.abc import Sequence

#: Stamp intervals on each side of a frame that give its local frame interval.
WINDOW = 15


def local_intervals(stamps_ns: Sequence[int]) -> list[int]:
    """For each frame after the first, the least time from the frame before it (ns): the lower quartile of the
    stamp intervals within :data:`WINDOW` of it (never below 0)."""
    deltas = [later - earlier for earlier, later in zip(stamps_ns, stamps_ns[1:])]
    intervals = []
    for index in range(len(deltas)):
        around = sorted(deltas[max(0, index - WINDOW):index + WINDOW + 1])
        intervals.append(max(0, around[len(around) // 4]))
    return intervals


def frame_times(stamps_ns: Sequence[int]) -> list[float]:
    """Each frame's time (ns, from the first stamp): the times closest to the stamps (least squares) in which every
    frame is at least its local interval after the one before; a regular stream's are its stamps."""
    if not stamps_ns:
        return []
    # With G the running sum of the minimum spacings, t - G must not decrease: fit v = stamp - G by a non-decreasing
    # sequence (pool adjacent violators: blocks of equal value, each the mean of its members), then add G back.
    offsets = [0]
    for interval in local_intervals(stamps_ns):
        offsets.append(offsets[-1] + interval)
    blocks: list[list[float]] = []  # [sum, count]
    for stamp, offset in zip(stamps_ns, offsets):
        blocks.append([float(stamp - stamps_ns[0] - offset), 1.0])
        while len(blocks) > 1 and blocks[-2][0] / blocks[-2][1] > blocks[-1][0] / blocks[-1][1]:
            total, count = blocks.pop()
            blocks[-1][0] += total
            blocks[-1][1] += count
    fitted = [total / count for total, count in blocks for _ in range(int(count))]
    return [value + offset for value, offset in zip(fitted, offsets)]
