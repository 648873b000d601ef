"""The container's resources over a soak run: resident memory, open file descriptors, threads.

They are sampled from /proc just before each load of the extra driver. A sample is taken at a comparable moment
when the container holds the rig, the player and one recorder (neither an extra driver nor a second recorder),
and that recorder is not behind: its backlog fits its cache, and the memory of its last backlog in the stall
reserve has gone back to the system (``memory_return_pending``; a disk stall's backlog is memory the recorder
holds on purpose, and gives back once written). Other samples are kept, marked, and left out. Over the
comparable samples after the warm-up:

* a least-squares slope, per hour;
* the thirds: the largest value of the last third of those samples may exceed the largest of the first third by
  at most a small margin (a recorder's file being finished on a thread of its own, with its descriptor open, is
  the normal variation between two samples);
* for RSS also the slope, bounded; fitted only over at least ``MIN_FIT_SPAN_S`` (shorter, a slope per hour is
  noise and the bound is N/A).
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from typing import Any, Optional

RSS_SLOPE_MIB_PER_HOUR = 20.0
#: last-third maximum over first-third maximum: at most this much more
MARGINS = {"rss_mib": 16.0, "fds": 4.0, "threads": 2.0}
UNITS = {"rss_mib": "MiB", "fds": "fds", "threads": "threads"}
MIN_FIT_SPAN_S = 600.0


@dataclass
class Sample:
    """One reading of the container process, ``t`` seconds after the churn started."""

    t: float
    rss_mib: float
    fds: int
    threads: int
    base: bool          # a comparable moment: no extra driver, one recorder
    loadavg: float      # the machine's 1-minute load average
    backlog_mib: float  # what the recorder held, not yet written (a stalled disk's share of the RSS)

    @classmethod
    def take(cls, pid: int, t: float, base: bool, backlog_bytes: int) -> "Sample":
        with open(f"/proc/{pid}/status") as status:
            rss = next(int(line.split()[1]) for line in status if line.startswith("VmRSS:"))
        return cls(t, rss / 1024.0, len(os.listdir(f"/proc/{pid}/fd")), len(os.listdir(f"/proc/{pid}/task")),
                   base, os.getloadavg()[0], backlog_bytes / 2**20)


def least_squares_slope(points: list[tuple[float, float]]) -> Optional[float]:
    """The least-squares slope of (x, y) points; None for fewer than two distinct x."""
    if len(points) < 2:
        return None
    mean_x = sum(x for x, _ in points) / len(points)
    mean_y = sum(y for _, y in points) / len(points)
    spread = sum((x - mean_x) ** 2 for x, _ in points)
    if spread == 0:
        return None
    return sum((x - mean_x) * (y - mean_y) for x, y in points) / spread


def slope_per_hour(points: list[tuple[float, float]]) -> Optional[float]:
    """The least-squares slope of (seconds, value) points, per hour."""
    slope = least_squares_slope(points)
    return None if slope is None else 3600.0 * slope


def thirds(points: list[tuple[float, float]]) -> tuple[float, float]:
    """The largest value among the first and among the last third of the points (by time)."""
    span = points[-1][0] - points[0][0]
    first = [v for t, v in points if t <= points[0][0] + span / 3]
    last = [v for t, v in points if t >= points[-1][0] - span / 3]
    return max(first), max(last)


def metric_report(samples: list[Sample], metric: str) -> dict[str, Any]:
    points = [(s.t, float(getattr(s, metric))) for s in samples]
    first_max, last_max = thirds(points)
    margin = MARGINS[metric]
    return {"start": points[0][1], "end": points[-1][1], "min": min(v for _, v in points),
            "max": max(v for _, v in points), "slope_per_hour": slope_per_hour(points),
            "first_third_max": first_max, "last_third_max": last_max, "margin": margin,
            "thirds_ok": last_max <= first_max + margin}


def evaluate(samples: list[Sample], warmup_s: float) -> dict[str, Any]:
    """Slopes, thirds and bounds over the comparable samples after the warm-up (module docstring)."""
    used = [s for s in samples if s.base and s.t >= warmup_s]
    out: dict[str, Any] = {"samples": [asdict(s) for s in samples], "used_samples": len(used),
                           "warmup_s": warmup_s}
    if len(used) < 3:
        out["bounds"] = [bound("enough samples after the warm-up", False, f"{len(used)} comparable samples")]
        return out
    span = used[-1].t - used[0].t
    out["fit_span_s"] = span
    out.update({metric: metric_report(used, metric) for metric in MARGINS})
    rss_slope = out["rss_mib"]["slope_per_hour"]
    bounds = [bound(f"RSS slope < {RSS_SLOPE_MIB_PER_HOUR:g} MiB/h",
                    None if span < MIN_FIT_SPAN_S else rss_slope < RSS_SLOPE_MIB_PER_HOUR,
                    f"{rss_slope:+.1f} MiB/h over {span / 60:.1f} min"
                    + (f" (a fit over less than {MIN_FIT_SPAN_S / 60:g} min is not judged)"
                       if span < MIN_FIT_SPAN_S else ""))]
    for metric in MARGINS:
        m = out[metric]
        unit = UNITS[metric]
        bounds.append(bound(f"{metric}: last-third max <= first-third max + {m['margin']:g} {unit}", m["thirds_ok"],
                            f"{m['last_third_max']:.1f} vs {m['first_third_max']:.1f} {unit}; slope "
                            f"{m['slope_per_hour']:+.1f} {unit}/h"))
    out["bounds"] = bounds
    return out


def bound(name: str, ok: Optional[bool], detail: str) -> dict[str, Any]:
    """One PASS / FAIL / N/A line of the report."""
    return {"bound": name, "result": "N/A" if ok is None else ("PASS" if ok else "FAIL"), "detail": detail}
