"""The benchmark's text report (the tables it prints as it finishes) and its optional plot.

Columns: **MB/s** = serialized bytes of the window's recorded messages / window seconds (MB = 1e6 bytes,
GB = 1e9 bytes); **% direct** = that as a percentage of the direct-write limit of the same run; **rec CPU s**
= the recorder's own CPU (dds: its process; ipc: ipc total minus drivers-only total); **writer s** = the
recorder's bag-writer thread alone; **tot CPU s** = every process of the mode; **kernel s** / **other s** =
CPU the machine spent outside the mode's processes (kernel threads and interrupts, the bag's writeback among
them; other people's processes); **peak RSS** = VmHWM of each process over its whole life.
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Any, Optional

from benchmarks.record.figures import good, total_us_per_msg
from benchmarks.record.measure import MB
from benchmarks.record.scenarios import PUBLISH_RATE_OK, RECORDER_MODES, Scenario


def fmt(value: Any, spec: str = ".1f", missing: str = "-") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return missing
    return format(value, spec)


def table(headers: list[str], rows: list[list[str]]) -> str:
    """A plain-text table: the first two columns left-aligned, the others right-aligned."""
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(headers)]
    line = lambda cells: "  ".join(c.ljust(w) if i < 2 else c.rjust(w)  # noqa: E731
                                   for i, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([line(headers), line(["-" * w for w in widths]), *(line(r) for r in rows)])


def topic_table(results: dict[str, Any]) -> str:
    rows = []
    for mode in RECORDER_MODES:
        entry = results.get(mode)
        if not good(entry):
            continue
        for name, c in entry["topics"].items():
            rows.append([mode, name, f"{c['published']}{'~' if c['estimated'] else ''}", str(c["recorded"]),
                         str(c["lost"]), fmt(100.0 * c["lost"] / c["published"] if c["published"] else 0.0, ".2f"),
                         fmt(100.0 * c["pub_ratio"], ".1f"), fmt(c["bytes"] / MB / entry["window_s"], ".1f")])
    return table(["mode", "topic", "published", "recorded", "lost", "lost %", "pub %nom", "MB/s"], rows)


def mode_row(mode: str, e: dict[str, Any]) -> list[str]:
    lat = e.get("latency_ms") or {}
    rss = e.get("peak_rss_mb") or {}
    return [mode, str(e.get("published", "-")), str(e.get("recorded", "-")),
            fmt(e.get("lost_pct"), ".2f"), fmt(e.get("mb_per_s"), ".1f"), fmt(e.get("direct_write_pct"), ".0f"),
            fmt(e.get("recorder_cpu_s"), ".2f"), fmt(e.get("writer_thread_cpu_s"), ".2f"),
            fmt(e.get("total_cpu_s"), ".2f"),
            fmt(sum(e["cpu_sys_s"].values()) if "cpu_sys_s" in e else None, ".2f"),
            fmt(e.get("recorder_cpu_s_per_gb"), ".2f"), fmt(e.get("total_cpu_s_per_gb"), ".2f"),
            "/".join(f"{v:.0f}" for v in rss.values()) if rss else "-",
            fmt(lat.get("p50"), ".1f"), fmt(lat.get("p99"), ".1f"), fmt(e.get("kernel_cpu_s"), ".1f"),
            fmt(e.get("background_cpu_s"), ".1f")]


def mode_table(results: dict[str, Any]) -> str:
    rows = []
    for mode in (*RECORDER_MODES, "drivers", "ceiling", "baseline"):
        e = results.get(mode)
        if e:
            rows.append([mode, "ERROR: " + e["error"][:60]] + [""] * 15 if "error" in e else mode_row(mode, e))
    return table(["mode", "published", "recorded", "lost %", "MB/s", "% direct", "rec CPU s", "writer s",
                  "tot CPU s", "sys s", "rec s/GB", "tot s/GB", "peak RSS MB", "lat p50 ms", "p99 ms",
                  "kernel s", "other s"], rows)


def recorder_notes(mode: str, e: dict[str, Any]) -> list[str]:
    out = []
    if e["min_pub_ratio"] < PUBLISH_RATE_OK:
        out.append(f"{mode}: drivers published only {100 * e['min_pub_ratio']:.1f} % of nominal on the worst "
                   f"topic (source skips logged: {e['source_skips_logged']})")
    if e["duplicates"]:
        out.append(f"{mode}: {e['duplicates']} duplicate messages in the bag")
    if not e["bag_matches_recorder_written"]:
        out.append(f"{mode}: bag holds {e['bag_messages']} messages but the recorder counted "
                   f"{sum(t.get('written', 0) for t in (e['recorder_counters'] or {}).values())} written")
    if e["recorder_error"]:
        out.append(f"{mode}: recorder error: {e['recorder_error']}")
    if e.get("dirty_threshold_mb") and e["peak_dirty_mb"] > 0.8 * e["dirty_threshold_mb"]:
        out.append(f"{mode}: the page cache held up to {e['peak_dirty_mb']:.0f} MB of unwritten data, near the "
                   f"kernel's dirty limit ({e['dirty_threshold_mb']:.0f} MB): writes get throttled to the "
                   "disk's writeback speed there")
    return out


def notes(results: dict[str, Any]) -> list[str]:
    out = [line for mode in RECORDER_MODES if good(results.get(mode)) for line in recorder_notes(mode, results[mode])]
    if results.get("ipc", {}).get("recorder_cpu_note"):
        out.append("ipc rec CPU = ipc total - drivers-only total (drivers and recorder share one process); "
                   "writer s = CPU of the recorder's bag-writer thread alone (intake runs on the executor thread)")
        if results["ipc"].get("recorder_cpu_subtraction_below_writer"):
            out.append("ipc: the subtraction came out below the writer thread's own CPU, so it is unreliable "
                       "(the executor's per-wake overhead is not additive); targets use the writer thread CPU")
    for mode in ("ipc", "dds", "drivers", "ceiling"):
        e = results.get(mode)
        if good(e) and (e.get("background_cpu_s") or 0) > 0.1 * e.get("window_s", 10) * (os.cpu_count() or 1):
            out.append(f"{mode}: other processes used {e['background_cpu_s']:.1f} CPU s during the window "
                       "(a busy machine: numbers are perturbed)")
        if e and e.get("attempts", 1) > 1:
            out.append(f"{mode}: run {e['attempts']} times because other processes perturbed it; the least "
                       "perturbed run is shown")
    if good(results.get("ceiling")):
        c = results["ceiling"]
        out.append(f"ceiling: {c['recorded_bytes'] / MB:.0f} MB in {c['messages']} writes, {c['write_s']:.2f} s "
                   f"({c['mb_per_s_with_fsync']:.0f} MB/s including a final fsync); median of "
                   + ", ".join(f"{v:.0f}" for v in c["all_runs_mb_per_s"]) + " MB/s at "
                   + ", ".join(f"{v:.2f}" for v in c["all_runs_cpu_s_per_gb"])
                   + f" CPU s/GB; warm (right after an unlink, reusing its pages): {c['warm_mb_per_s']:.0f} MB/s at "
                   f"{c['warm_cpu_s_per_gb']:.2f} CPU s/GB")
    return out


def verdict(step: dict[str, Any]) -> str:
    if step["lossless"]:
        return "yes"
    reasons = []
    if step["lost"]:
        reasons.append("lost")
    if step["min_pub_ratio"] < PUBLISH_RATE_OK:
        reasons.append("drivers slow")
    if step["recorder_error"]:
        reasons.append("error")
    return "NO (" + ", ".join(reasons) + ")"


def print_repeat(repeat: dict[str, Any]) -> None:
    runs = repeat["results"]
    print(f"\n== S1 repeated: {len(runs)} runs back to back (run 1 is the one shown in full above)")
    rows = []
    for number, run in enumerate(runs, 1):
        for mode, e in run.items():
            if "error" in e:
                rows.append([str(number), mode, "ERROR " + e["error"][:50]] + [""] * 8)
                continue
            rows.append([str(number), mode, str(e["published"]), str(e["lost"]), fmt(e["lost_pct"], ".2f"),
                         fmt(e["mb_per_s"], ".1f"), fmt(e.get("direct_write_pct"), ".0f"),
                         fmt(e.get("total_cpu_s_per_gb"), ".2f"), fmt((e.get("latency_ms") or {}).get("p99"), ".1f"),
                         fmt(e.get("kernel_cpu_s"), ".1f"), verdict(e)])
    print(table(["run", "mode", "published", "lost", "lost %", "MB/s", "% direct", "tot s/GB", "p99 ms", "kernel s",
                 "lossless"], rows))
    for mode, m in repeat["per_mode"].items():
        print(f"  {mode}: lossless in {m['lossless_runs']} of {m['runs']} runs"
              + (f" ({m['failed_runs']} failed)" if m["failed_runs"] else "")
              + f"; lost % min {fmt(m['lost_pct_min'], '.2f')} / median {fmt(m['lost_pct_median'], '.2f')} / "
              f"max {fmt(m['lost_pct_max'], '.2f')}")
    if repeat["ipc_dds_cpu_per_gb_ratio"] is not None:
        print("  ipc / dds total CPU s/GB per run: "
              + ", ".join(fmt(r, ".2f") for r in repeat["ipc_dds_cpu_per_gb_ratio"]))
    if repeat["split_ipc_p99_ratio"] is not None:
        print("  split / ipc receive-to-write p99 per run: "
              + ", ".join(fmt(r, ".2f") for r in repeat["split_ipc_p99_ratio"]))


def print_direct(report: dict[str, Any]) -> None:
    d = report["direct_write"]
    if "error" in d:
        print(f"\n== Direct-write limit: ERROR {d['error']}")
        return
    ceiling = (report.get("S1") or {}).get("ceiling") or {}
    print(f"\n== Direct-write limit of {d['path']}: {d['mb_per_s']:.0f} MB/s (O_DIRECT, {d['bytes'] / 2**20:.0f} MiB "
          f"in {d['block_bytes'] // 2**20} MiB blocks + fsync, {d['cpu_s_per_gb']:.2f} CPU s/GB; median of "
          + ", ".join(f"{v:.0f}" for v in d["all_runs_mb_per_s"]) + " MB/s)"
          + (f"; buffered ceiling (S1) {ceiling['mb_per_s']:.0f} MB/s = {ceiling['direct_write_pct']:.0f} % of it"
             if "direct_write_pct" in ceiling else ""))


def print_s1(s1: dict[str, Any], scenario: Scenario, args: argparse.Namespace) -> None:
    print(f"\n== {scenario.title}: {scenario.describe()}; {args.storage}, cache {args.cache_mb:g} MiB, "
          f"executor {args.executor}")
    print(topic_table(s1))
    print()
    print(mode_table(s1))
    for line in notes(s1):
        print("  * " + line)
    if "repeat" in s1:
        print_repeat(s1["repeat"])


def print_s2(s2: dict[str, Any]) -> None:
    print(f"\n== S2 ramp: +1 camera per step, {s2['base']}, cap {s2['cap']}, {s2['seconds']:g} s windows")
    rows = []
    for step in s2["steps"]:
        if "error" in step:
            rows.append([step["mode"], str(step["cameras"]), "ERROR " + step["error"][:50]] + [""] * 11)
            continue
        rows.append([step["mode"], str(step["cameras"]), str(step["lost"]), fmt(step["lost_pct"], ".2f"),
                     fmt(100 * step["min_pub_ratio"], ".1f"), fmt(step["mb_per_s"], ".1f"),
                     fmt(step.get("direct_write_pct"), ".0f"), fmt(step.get("peak_backlog_mb"), ".0f"),
                     fmt(step.get("end_backlog_mb"), ".0f"),
                     "" if step.get("within_cache") is None else ("yes" if step["within_cache"] else "no"),
                     fmt(step["total_cpu_s"], ".2f"), fmt(step.get("kernel_cpu_s"), ".1f"),
                     fmt(step.get("background_cpu_s"), ".1f"), verdict(step)])
    print(table(["mode", "cameras", "lost", "lost %", "min pub %nom", "MB/s", "% direct", "backlog peak", "at end",
                 "in cache", "tot CPU s", "kernel s", "other s", "lossless"], rows))
    for mode, best in s2["largest_lossless"].items():
        print(f"  largest lossless camera count, {mode}: {best}"
              + ("" if s2["limit_reached"].get(mode) else f" (no loss up to the cap of {s2['cap']})"))
    if s2.get("repeat"):
        print_s2_repeat(s2["repeat"])
    if s2.get("ceiling"):
        c = s2["ceiling"]
        print(f"  ceiling for the ipc overload step ({c['cameras']} cameras): {c['mb_per_s']:.0f} MB/s (median of "
              + ", ".join(f"{v:.0f}" for v in c["all_runs_mb_per_s"])
              + f"; warm, reusing just-freed pages: {c['warm_mb_per_s']:.0f} MB/s)")


def print_s2_repeat(repeat: dict[str, Any]) -> None:
    print(f"\n== S2 repeated: ipc with {repeat['cameras']} cameras, {repeat['runs']} runs back to back")
    rows = []
    for number, run in enumerate(repeat["results"], 1):
        if "error" in run:
            rows.append([str(number), "ERROR " + run["error"][:50]] + [""] * 6)
            continue
        rows.append([str(number), str(run["published"]), str(run["lost"]), fmt(run["mb_per_s"], ".1f"),
                     fmt(run.get("direct_write_pct"), ".0f"), fmt(run["recorder_rss_mb"], ".0f"),
                     fmt((run.get("latency_ms") or {}).get("p99"), ".1f"), verdict(run)])
    print(table(["run", "published", "lost", "MB/s", "% direct", "peak RSS MB", "p99 ms", "lossless"], rows))
    print(f"  lossless in {repeat['lossless_runs']} of {repeat['runs']} runs")


def print_s3(s3: dict[str, Any], scenario: Scenario) -> None:
    print(f"\n== {scenario.title}: {scenario.describe()}")
    print(mode_table(s3))
    for mode in ("ipc", "dds"):
        e = s3.get(mode)
        if good(e):
            print(f"  {mode}: recorder CPU per recorded message: {fmt(e.get('recorder_cpu_us_per_msg'), '.1f')} us"
                  + (" (ipc total - drivers only)" if mode == "ipc" else "")
                  + f"; writer thread alone {fmt(e.get('writer_thread_us_per_msg'), '.1f')} us"
                  + f" ({e['recorded']} messages, lost {e['lost']})")
    baseline, ipc = s3.get("baseline"), s3.get("ipc")
    if good(baseline) and good(ipc):
        print(f"  total CPU per recorded message: ipc {total_us_per_msg(ipc):.1f} us, the code at "
              f"{baseline['code']} (single executor) {total_us_per_msg(baseline):.1f} us "
              f"({baseline['recorded']} messages, drivers at >= {100 * baseline['min_pub_ratio']:.0f} % of "
              f"nominal): {total_us_per_msg(baseline) / total_us_per_msg(ipc):.2f}x lower")
    for line in notes(s3):
        print("  * " + line)


def s4_row(step: dict[str, Any]) -> list[str]:
    """One S4 run: frames, bytes, PSNR (beside raw), CPU per camera, latency, hours per TB."""
    label = step["codec"] + (" + raw" if step.get("beside") else "")
    if "error" in step:
        return [label, str(step["cameras"]), "ERROR " + step["error"][:50]] + [""] * 10
    lat = step.get("latency_ms") or {}
    quality = (step.get("psnr") or {}).get("psnr_db")
    return [label, str(step["cameras"]), f"{step['lost']}/{step['published']}", fmt(step.get("encoder_skipped"), "d"),
            fmt(100 * step["min_pub_ratio"], ".1f"), fmt(step["mb_per_s"], ".2f"), fmt(step["raw_pct"], ".2f"),
            fmt(quality, ".1f"), fmt(step["cpu_per_camera"], ".2f"), fmt(lat.get("p50"), ".1f"),
            fmt(lat.get("p99"), ".1f"), fmt(step["hours_per_tb"], ".1f"), "yes" if step["lossless"] else "NO"]


def sizing_lines(s4: dict[str, Any]) -> list[str]:
    """What one 1080p30 camera costs per codec, one sentence each."""
    lines = []
    for codec, c in s4.get("sizing", {}).items():
        lines.append(f"{codec}: {c['cpu_per_camera']:.2f} CPU cores (driver, encoder and recorder), "
                     f"{c['mb_per_s_per_camera']:.2f} MB/s ({c['raw_pct']:.2f} % of raw"
                     + (f", {c['psnr_db']:.1f} dB" if c.get("psnr_db") is not None else "")
                     + f"), {c['hours_per_tb_per_camera']:.0f} h per TB; {c['largest_lossless']} camera(s) "
                     + ("without loss" if c["limit_reached"] else f"without loss up to the cap of {s4['cap']}"))
    return lines


def s4_steps(s4: dict[str, Any]) -> list[dict[str, Any]]:
    """The ramps' runs by codec (in --s4-codecs order) and camera count, not in the order the search ran them."""
    return sorted(s4["steps"], key=lambda step: (s4["codecs"].index(step["codec"]), step["cameras"]))


def limit_lines(s4: dict[str, Any]) -> list[str]:
    """Per compressed codec: its codec limit, how it was measured, and how close its ramp came to it."""
    limits = s4.get("limits") or {}
    if "error" in limits:
        return [f"codec limits: ERROR {limits['error']}"]
    lines = []
    for label, limit in (limits.get("codecs") or {}).items():
        count = s4["largest_lossless"].get(label, 0)
        lines.append(f"{label}: codec limit {limit['cameras']:.2f} cameras = {limits['cores']} cores x "
                     f"{limits['frame_interval_ms']:.1f} ms / {limit['ms_per_frame']:.2f} ms {limit['clock']} CPU per "
                     f"frame (thread {limit['thread_ms_per_frame']:.2f}, process {limit['process_ms_per_frame']:.2f} "
                     f"ms over {limit['frames']} frames); {count} camera(s) without loss = "
                     f"{100 * count / limit['cameras']:.0f} % of it")
    return lines


def search_text(s4: dict[str, Any]) -> str:
    """How a run's ramps chose their camera counts (camera_search.py)."""
    raw = f"; raw from {s4['caps']['raw']} down" if "raw" in s4["caps"] else ""
    return f"per codec the largest camera count without loss, searched from its codec limit (cap {s4['cap']}{raw})"


def print_s4(s4: dict[str, Any]) -> None:
    print(f"\n== {s4['scenario']['title'].split(',')[0]}: {s4['scenario']['describe']}; {search_text(s4)}; each "
          "codec beside raw")
    print(table(["codec", "cameras", "lost/published", "enc skipped", "min pub %nom", "MB/s", "% raw", "PSNR dB",
                 "CPU/camera", "lat p50 ms", "p99 ms", "h per TB", "lossless"],
                [s4_row(step) for step in [*s4_steps(s4), *s4["beside"]]]))
    for line in limit_lines(s4):
        print("  " + line)
    for run in s4["beside"]:
        if good(run):
            p = run["psnr"]
            print(f"  beside {run['codec']}: raw lost {run['raw']['lost']} of {run['raw']['published']}; PSNR over "
                  f"{p['frames']} frames of camera 0, lowest frame {fmt(p['psnr_min_db'], '.1f')} dB"
                  + (f", {p['unmatched']} raw frames without a decoded frame" if p["unmatched"] else ""))
    print("  one 1080p30 camera costs:")
    for line in sizing_lines(s4):
        print("    " + line)


def print_report(report: dict[str, Any], args: argparse.Namespace, scenarios: dict[str, Scenario]) -> None:
    """Every table of the run, the targets and a closing line (code measured, run time)."""
    if "direct_write" in report:
        print_direct(report)
    if "S1" in report:
        print_s1(report["S1"], scenarios["S1"], args)
    if "S2" in report:
        print_s2(report["S2"])
    if "S3" in report:
        print_s3(report["S3"], scenarios["S3"])
    if "S4" in report:
        print_s4(report["S4"])
    print("\n== Targets")
    for t in report["targets"]:
        print(f"  {t['result']:4}  {t['target']}: {t['detail']}")
    git = report["git"]
    print(f"\n(total run time {report['elapsed_s']:.0f} s; code at {git['commit']}"
          + (f" + uncommitted changes in {', '.join(git['modified'])}" if git["modified"] else "")
          + "; 'kernel s' = CPU of kernel threads and interrupts during the window (the writeback of the "
          "bag among them), 'other s' = CPU of other people's processes)", flush=True)


def bar_panels(report: dict[str, Any]) -> list[tuple[str, list[str], list[float]]]:
    """(title, labels, values) of the bar charts: S1 MB/s and CPU per GB, S3 recorder CPU per message."""
    panels = []
    s1 = report.get("S1") or {}
    modes = [m for m in ("ipc", "dds", "ceiling") if good(s1.get(m))]
    if modes:
        panels.append(("S1 recorded MB/s", modes, [s1[m]["mb_per_s"] for m in modes]))
        cpu_modes = [m for m in modes if s1[m].get("total_cpu_s_per_gb")]
        panels.append(("S1 total CPU s per recorded GB", cpu_modes, [s1[m]["total_cpu_s_per_gb"] for m in cpu_modes]))
    s3 = report.get("S3") or {}
    s3_modes = [m for m in ("ipc", "dds") if good(s3.get(m)) and s3[m].get("recorder_cpu_best_us_per_msg") is not None]
    if s3_modes:
        panels.append(("S3 recorder CPU us per message", s3_modes,
                       [s3[m]["recorder_cpu_best_us_per_msg"] for m in s3_modes]))
    return panels


def plot_s2(ax: Any, s2: dict[str, Any]) -> None:
    from matplotlib.ticker import MaxNLocator
    for mode, color in (("ipc", "tab:green"), ("dds", "tab:red")):
        steps = [s for s in s2["steps"] if s["mode"] == mode and good(s)]
        if steps:
            ax.plot([s["cameras"] for s in steps], [s["mb_per_s"] for s in steps], "o-", color=color,
                    label=f"{mode} MB/s")
            lossy = [s for s in steps if not s["lossless"]]
            ax.plot([s["cameras"] for s in lossy], [s["mb_per_s"] for s in lossy], "x", color="black", markersize=10)
    if s2.get("ceiling"):
        ax.axhline(s2["ceiling"]["mb_per_s"], color="tab:gray", linestyle="--", label="ceiling")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("cameras (x = lossy step)")
    ax.set_title("S2 ramp: recorded MB/s", fontsize=10)
    ax.legend(fontsize=8)


def plot(report: dict[str, Any], path: Path) -> Optional[Path]:
    """A PNG of the main figures; None when matplotlib is not installed or there is nothing to plot."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    panels = bar_panels(report)
    s2 = report.get("S2")
    count = len(panels) + (1 if s2 else 0)
    if not count:
        return None
    fig, axes = plt.subplots(1, count, figsize=(4.5 * count, 4))
    axes = [axes] if count == 1 else list(axes)
    for ax, (title, labels, values) in zip(axes, panels):
        ax.bar(labels, values, color=["tab:green", "tab:red", "tab:gray"][:len(labels)])
        ax.set_title(title, fontsize=10)
    if s2:
        plot_s2(axes[-1], s2)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
