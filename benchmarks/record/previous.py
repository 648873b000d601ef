"""This run against the previous result file of the same rig: did a figure get worse by more than the noise?

Why: CPU per GB doubled between two committed result files and nobody compared them. Every run now looks up the
newest ``record.json`` under the results directory that was started before it and measured the same rig (S1: the
same drivers, storage, cache and executor; S4: the same cameras, storage and executor), and compares the figures
of :data:`FIGURES` (S1) and :func:`s4_figures` (S4: per codec, the largest lossless camera count and the codec's
CPU time per frame). A figure is worse when it is beyond the previous one by more than the noise: the relative
spread (max - min over the median) of that figure over this run's ``--repeat`` runs, else over the previous
file's, and never less than :data:`NOISE_FLOOR` (S4 runs once: the floor).

Absolute CPU times also change with the machine (a different virtual machine, its host's load), not only with
the code: each result file names its CPU and kernel, and the comparison says when they differ. A figure worse
on the same machine is a regression to bisect; on another machine, run both commits side by side first.
"""
from __future__ import annotations

import json
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

from benchmarks.record.figures import cpu_per_gb_ratio, good

#: Never call a change below this share noise, whatever --repeat showed.
NOISE_FLOOR = 0.10
#: The configuration that makes two S1 runs the same rig (the window length is not among them: every figure
#: compared is per GB or per second).
SAME_RIG = ("cameras", "width", "height", "fps", "lidar_points", "lidar_rate", "imu_rate", "storage", "cache_mb",
            "executor")
#: The same for S4 (the camera counts are what the runs find).
SAME_S4 = ("width", "height", "fps", "storage", "executor")


def _drivers_cpu_per_s(s1: dict[str, Any]) -> Optional[float]:
    drivers = s1.get("drivers")
    return drivers["total_cpu_s"] / drivers["window_s"] if good(drivers) and drivers.get("window_s") else None


def _mode_figure(mode: str, key: str) -> Callable[[dict[str, Any]], Optional[float]]:
    return lambda s1: s1[mode].get(key) if good(s1.get(mode)) else None


#: (name, how to read it from an S1 block or one --repeat run): lower is better for every one.
FIGURES: tuple[tuple[str, Callable[[dict[str, Any]], Optional[float]]], ...] = (
    ("ipc total CPU s/GB", _mode_figure("ipc", "total_cpu_s_per_gb")),
    ("ipc recorder's own CPU s/GB", _mode_figure("ipc", "recorder_cpu_s_per_gb")),
    ("dds total CPU s/GB", _mode_figure("dds", "total_cpu_s_per_gb")),
    ("ipc / dds CPU per GB", lambda s1: cpu_per_gb_ratio(s1.get("ipc"), s1.get("dds"))),
    ("drivers-only CPU s/s", _drivers_cpu_per_s),
)


@dataclass(frozen=True)
class Change:
    """One figure of this run against the previous file's."""

    name: str
    previous: float
    current: float
    noise: float  # relative
    higher_is_better: bool = False

    @property
    def worse(self) -> bool:
        if self.higher_is_better:
            return self.current < self.previous * (1 - self.noise)
        return self.current > self.previous * (1 + self.noise)

    def text(self) -> str:
        change = 100 * (self.current / self.previous - 1)
        return (f"{self.name} {self.current:.2f} vs {self.previous:.2f} ({change:+.0f} %, noise "
                f"{100 * self.noise:.0f} %)" + (" WORSE" if self.worse else ""))


def measured(report: dict[str, Any], part: str) -> bool:
    """Whether a run has figures of ``part`` to compare: S1 ipc, or an S4 ramp step."""
    if part == "S1":
        return good((report.get("S1") or {}).get("ipc"))
    return any(good(step) for step in (report.get("S4") or {}).get("steps", []))


def same_rig(a: dict[str, Any], b: dict[str, Any], keys: tuple[str, ...] = SAME_RIG) -> bool:
    """Whether two runs' configurations agree on ``keys``: the same S1 rig, storage and executor by default."""
    return all(a.get("config", {}).get(key) == b.get("config", {}).get(key) for key in keys)


def find_previous(results: Path, report: dict[str, Any], part: str = "S1") -> Optional[tuple[Path, dict[str, Any]]]:
    """The newest ``record.json`` under ``results`` started before ``report`` with ``part`` (S1, S4) measured on
    the same rig; None if there is none."""
    keys = SAME_RIG if part == "S1" else SAME_S4
    found: list[tuple[str, Path, dict[str, Any]]] = []
    for path in results.glob("*/record.json"):
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        started = record.get("started_at", "")
        if started < report.get("started_at", "") and measured(record, part) and same_rig(record, report, keys):
            found.append((started, path, record))
    if not found:
        return None
    _, path, record = max(found, key=lambda item: item[0])
    return path, record


def spread(values: list[float]) -> Optional[float]:
    """(max - min) / median of at least two values; None with fewer."""
    if len(values) < 2 or statistics.median(values) <= 0:
        return None
    return (max(values) - min(values)) / statistics.median(values)


def repeat_noise(s1: dict[str, Any], read: Callable[[dict[str, Any]], Optional[float]]) -> Optional[float]:
    """The spread of one figure over an S1 block's --repeat runs (None without repeats). The drivers-only mode
    runs once per S1: its figure shows no spread, and only the floor and the other file's repeats apply."""
    runs = (s1.get("repeat") or {}).get("results") or []
    values = [value for run in runs if (value := read({**run, "drivers": s1.get("drivers")})) is not None]
    return spread(values)


def compare(current: dict[str, Any], previous: dict[str, Any]) -> list[Change]:
    """Every figure of :data:`FIGURES` both runs' S1 have, with its noise."""
    s1, before = current.get("S1") or {}, previous.get("S1") or {}
    changes = []
    for name, read in FIGURES:
        now, then = read(s1), read(before)
        if now is None or not then:
            continue
        noise = [value for value in (repeat_noise(s1, read), repeat_noise(before, read)) if value is not None]
        changes.append(Change(name, then, now, max([NOISE_FLOOR, *noise[:1]])))
    return changes


def s4_figures(s4: dict[str, Any]) -> dict[str, tuple[float, bool, bool]]:
    """Per codec of an S4 block: its largest lossless camera count and (from runs that measured it) its codec's
    CPU time per frame, as ``name: (value, higher is better, only a lower bound)``: a ramp that stopped at its cap
    without loss says no more than that the count is at least its cap."""
    limits = (s4.get("limits") or {}).get("codecs") or {}
    figures = {f"{label} cameras without loss": (float(count), True, not s4.get("limit_reached", {}).get(label, True))
               for label, count in s4.get("largest_lossless", {}).items()}
    figures.update({f"{label} codec CPU ms per frame": (limit["ms_per_frame"], False, False)
                    for label, limit in limits.items()})
    return figures


def compare_s4(current: dict[str, Any], previous: dict[str, Any]) -> list[Change]:
    """Every figure of :func:`s4_figures` both runs' S4 have; not a previous count of 0 (nothing to beat), nor a
    count this run's cap kept below the previous one."""
    now, then = s4_figures(current.get("S4") or {}), s4_figures(previous.get("S4") or {})
    return [Change(name, then[name][0], value, NOISE_FLOOR, higher)
            for name, (value, higher, bound) in now.items()
            if then.get(name, (0.0,))[0] and not (bound and value < then[name][0])]


#: How each part is compared: S1's figures, S4's.
COMPARE: dict[str, Callable[[dict[str, Any], dict[str, Any]], list[Change]]] = {"S1": compare, "S4": compare_s4}


def machine(report: dict[str, Any]) -> str:
    """The CPU and kernel a run names ('unknown' for files written before runs named them)."""
    environment = report.get("environment", {})
    return f"{environment.get('cpu_model', 'unknown CPU')}, kernel {environment.get('kernel', 'unknown')}"
