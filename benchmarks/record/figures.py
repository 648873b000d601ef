"""Figures derived from several modes' results of one run: the ipc recorder's CPU (by subtraction), shares of
the direct-write limit, the ratios the targets compare and the distribution of ``--repeat`` runs."""
from __future__ import annotations

import statistics
from typing import Any, Optional

from benchmarks.record.measure import GB
from benchmarks.record.scenarios import IPC_MODES, RECORDER_MODES


def good(entry: Optional[dict[str, Any]]) -> bool:
    """A mode that ran and produced results."""
    return entry is not None and "error" not in entry


def total_us_per_msg(entry: dict[str, Any]) -> float:
    """Drivers and recorder: the container's whole CPU in the window per recorded message."""
    return 1e6 * entry["total_cpu_s"] / max(1, entry["recorded"])


def apply_recorder_cpu(results: dict[str, Any]) -> None:
    """The recorder's own CPU: ``dds``: the recorder process; ``ipc`` and ``split``: their total minus the
    drivers-only total. That is what a user whose drivers are already running pays for recording.

    The subtraction assumes the drivers cost the same with and without the recorder next to them; the rclpy
    executor's per-wake overhead shrinks when it is busier, so it can come out below the bag writer thread's
    own CPU (which the recorder certainly spent): then the writer thread is the estimate (``..._best``).
    """
    drivers = results.get("drivers")
    for mode in IPC_MODES:
        entry = results.get(mode)
        if not good(entry) or not good(drivers):
            continue
        scale = entry["window_s"] / drivers["window_s"]
        entry["recorder_cpu_s"] = entry["total_cpu_s"] - drivers["total_cpu_s"] * scale
        entry["recorder_cpu_note"] = f"{mode} total minus drivers-only total"
        writer = entry.get("writer_thread_cpu_s")
        entry["recorder_cpu_subtraction_below_writer"] = writer is not None and entry["recorder_cpu_s"] < writer
        entry["recorder_cpu_best_s"] = max(entry["recorder_cpu_s"], writer or 0.0)
    dds = results.get("dds")
    if good(dds) and dds.get("recorder_cpu_s") is not None:
        dds["recorder_cpu_best_s"] = dds["recorder_cpu_s"]
    for mode in (*IPC_MODES, "dds"):
        entry = results.get(mode)
        if not good(entry) or entry.get("recorder_cpu_s") is None:
            continue
        if entry["recorded_bytes"]:
            entry["recorder_cpu_s_per_gb"] = entry["recorder_cpu_s"] / (entry["recorded_bytes"] / GB)
        if entry["recorded"]:
            entry["recorder_cpu_us_per_msg"] = 1e6 * entry["recorder_cpu_s"] / entry["recorded"]
            entry["recorder_cpu_best_us_per_msg"] = 1e6 * entry["recorder_cpu_best_s"] / entry["recorded"]
            if entry.get("writer_thread_cpu_s") is not None:
                entry["writer_thread_us_per_msg"] = 1e6 * entry["writer_thread_cpu_s"] / entry["recorded"]


def apply_direct_share(report: dict[str, Any]) -> None:
    """Every ipc row's MB/s (and each buffered ceiling's) as a percentage of the direct-write limit."""
    direct = report.get("direct_write")
    if not good(direct):
        return
    entries: list[Optional[dict[str, Any]]] = []
    for key in ("S1", "S3"):
        block = report.get(key) or {}
        entries += [block.get(mode) for mode in (*IPC_MODES, "ceiling")]
        for run in (block.get("repeat") or {}).get("results", []):
            entries += [run.get(mode) for mode in IPC_MODES]
    s2 = report.get("S2") or {}
    entries += [step for step in s2.get("steps", []) if step.get("mode") in IPC_MODES]
    entries += (s2.get("repeat") or {}).get("results", [])
    entries.append(s2.get("ceiling"))
    for entry in entries:
        if good(entry) and entry.get("mb_per_s"):
            entry["direct_write_pct"] = 100.0 * entry["mb_per_s"] / direct["mb_per_s"]


def cpu_per_gb_ratio(ipc: Optional[dict[str, Any]], dds: Optional[dict[str, Any]]) -> Optional[float]:
    """ipc total CPU s/GB over dds total CPU s/GB, None when either is missing or failed."""
    if not good(ipc) or not good(dds):
        return None
    a, b = ipc.get("total_cpu_s_per_gb"), dds.get("total_cpu_s_per_gb")
    return a / b if a and b else None


def p99_ratio(split: Optional[dict[str, Any]], ipc: Optional[dict[str, Any]]) -> Optional[float]:
    """split over unsplit receive-to-write latency p99, None when either is missing or failed."""
    a, b = ((e.get("latency_ms") or {}).get("p99") if good(e) else None for e in (split, ipc))
    return a / b if a and b else None


def repeat_summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The loss distribution of --repeat runs of S1 per recorder mode, the ipc / dds CPU ratio and the
    split / ipc latency p99 ratio per run."""
    per_mode: dict[str, Any] = {}
    for mode in RECORDER_MODES:
        entries = [run[mode] for run in runs if mode in run]
        if not entries:
            continue
        pcts = [e["lost_pct"] for e in entries if "error" not in e]
        per_mode[mode] = {"runs": len(entries), "failed_runs": len(entries) - len(pcts),
                          "lossless_runs": sum(1 for e in entries if "error" not in e and e["lossless"]),
                          "lost_pct_min": min(pcts, default=None), "lost_pct_max": max(pcts, default=None),
                          "lost_pct_median": statistics.median(pcts) if pcts else None}
    both = "ipc" in per_mode and "dds" in per_mode
    split = "ipc" in per_mode and "split" in per_mode
    return {"per_mode": per_mode,
            "ipc_dds_cpu_per_gb_ratio": [cpu_per_gb_ratio(r.get("ipc"), r.get("dds")) for r in runs] if both else None,
            "split_ipc_p99_ratio": [p99_ratio(r.get("split"), r.get("ipc")) for r in runs] if split else None}


def s2_repeat_summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """How many of S2's repeated ipc runs were lossless, and their peak RSS range."""
    rss = [run["recorder_rss_mb"] for run in runs if good(run)]
    return {"runs": len(runs), "failed_runs": sum(1 for run in runs if not good(run)),
            "lossless_runs": sum(1 for run in runs if good(run) and run["lossless"]),
            "peak_rss_mb_max": max(rss, default=None)}
