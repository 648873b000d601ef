"""S4's ramp: the largest camera count a codec records without loss, in a few runs, to the camera.

Why: doubling (1, 2, 4, 8 ...) cannot tell 4 cameras from 7, and stepping by one from 1 costs a run (half a minute
or more with its pauses) per camera. The search starts near the answer: at the smallest count that reaches the
target share of the codec limit measured in the same run (benchmarks/record/codec_limit.py), or at the cap for a
codec without a limit (raw). From there it steps by one camera, up while runs are lossless or down while they
lose frames, doubling the step while the outcome stays the same (a start far off costs a few runs, not one per
camera), then halves the gap between the largest lossless count and the smallest lossy count above it, until the
two are one camera apart or the largest lossless count is the cap. A lossy run also says how many cameras' worth
of frames it kept up with (``kept``: its cameras times the share of their frames recorded): where that is below
the next step and not below the largest lossless count, the search goes there (at least one camera above it)
instead. Near the estimate that is two or three runs.

``outcomes`` maps each camera count run to whether that run was lossless. Runs are noisy near the limit: the
answer is the largest lossless count, bracketed by a lossy run one camera above it.
"""
from __future__ import annotations

import math
from typing import Optional


def start_count(limit: Optional[float], share: float, cap: int) -> int:
    """The first count: the smallest reaching ``share`` of ``limit`` cameras, within 1 ... ``cap``; without a
    limit, the cap."""
    if limit is None:
        return cap
    return max(1, min(cap, math.ceil(share * limit)))


def largest_lossless(outcomes: dict[int, bool]) -> int:
    """The largest count run without loss (0: none)."""
    return max((count for count, lossless in outcomes.items() if lossless), default=0)


def lossy_above(outcomes: dict[int, bool]) -> Optional[int]:
    """The smallest count that lost frames above the largest lossless one (None: none did)."""
    best = largest_lossless(outcomes)
    return min((count for count, lossless in outcomes.items() if not lossless and count > best), default=None)


def next_count(outcomes: dict[int, bool], start: int, cap: int,
               kept: Optional[dict[int, float]] = None) -> Optional[int]:
    """The next camera count to run, or None once the largest lossless count is bracketed (module docstring);
    ``kept``: per lossy count run, the cameras' worth of frames it recorded."""
    if not outcomes:
        return start
    best, lossy = largest_lossless(outcomes), lossy_above(outcomes)
    if lossy is None:
        lossless_runs = sum(outcomes.values())
        return None if best >= cap else min(cap, best + 2 ** (lossless_runs - 1))
    if lossy == best + 1:
        return None
    lossy_runs = len(outcomes) - sum(outcomes.values())
    step = max(1, lossy - 2 ** (lossy_runs - 1)) if best == 0 else (best + lossy) // 2
    if kept and lossy in kept and math.floor(kept[lossy]) >= best:
        return min(step, max(math.floor(kept[lossy]), best + 1))
    return step
