"""The pass/fail targets. Each compares figures measured side by side in the same run (a ratio of two modes, or
of a mode and a limit measured on the same disk), never an absolute time: the machine and its load change the
absolute numbers, much less the ratios.

A target is PASS, FAIL, or N/A when the run did not measure what it compares (a scenario or mode not selected,
a mode that failed, a ramp capped before the recorder lost anything).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Optional

from benchmarks.record.figures import good, total_us_per_msg
from benchmarks.record.previous import COMPARE, find_previous, machine, measured
from benchmarks.record.report import fmt
from benchmarks.record.scenarios import PUBLISH_RATE_OK
from benchmarks.result_folder import RESULTS

DEFAULT_CACHE = 100 * 1024 * 1024  # rosbag2's storage.max_cache_size default
S1_CPU_RATIO = 0.5            # S1: ipc total CPU per GB at most half of dds's
SPLIT_P99_RATIO = 2.0         # S1: splitting at most doubles the receive-to-write p99
RSS_MARGIN_MIB = 300          # S1: the ipc container's peak RSS below max_cache_size plus this
S2_CAMERAS_RATIO = 2          # S2: ipc records at least twice as many cameras without loss as dds
S2_DIRECT_SHARE_PCT = 85      # S2: ipc lossless at >= this % of the direct-write limit of the same run
S2_CAMERAS = 5                # S2: ipc records this many 1080p30 cameras (with the LiDAR and IMU) without loss
OVERLOAD_CEILING_SHARE = 0.7  # S2: past its lossless limit, ipc still writes >= this share of the ceiling
S3_RECORDER_RATIO = 1 / 3     # S3: the ipc recorder's CPU per message at most a third of the dds recorder's
S3_BASELINE_RATIO = 0.5       # S3: drivers + recorder CPU per message at most half of --baseline's
#: S4, per codec at the encoder's defaults: (at most % of the raw bytes, at least PSNR dB, at least cameras
#: without loss, drivers included)
S4_CODEC_TARGETS = {"jpeg": (15.0, 38.0, 4), "h264": (3.0, 36.0, 1)}
#: S4, per codec of S4_CODEC_TARGETS: the largest lossless camera count (drivers included) at least this share of
#: the codec limit of the same run (cores x frame interval / the codec's own CPU time per frame, codec_limit.py)
S4_LIMIT_SHARE = 0.85
#: S4's moonshot, reported beside that target: 1080p30 cameras without loss on the reference machine's 2 cores
S4_MOONSHOT = {"jpeg": 6, "h264": 3}
REPEAT_RUNS = 5               # --repeat: ipc lossless in every one of at least this many runs
REPEAT_CPU_RATIO = 0.33       # --repeat: ipc / dds total CPU per GB in every run


class Targets:
    def __init__(self) -> None:
        self.rows: list[dict[str, Any]] = []

    def add(self, name: str, ok: Optional[bool], detail: str) -> None:
        self.rows.append({"target": name, "result": "N/A" if ok is None else ("PASS" if ok else "FAIL"),
                          "detail": detail})


def default_storage(args: argparse.Namespace) -> bool:
    return args.storage == "mcap" and args.cache_mb * 1024 * 1024 == DEFAULT_CACHE


def without_loss(entry: dict[str, Any]) -> bool:
    return entry["lost"] == 0 and entry["min_pub_ratio"] >= PUBLISH_RATE_OK


def s1_targets(s1: dict[str, Any], args: argparse.Namespace, targets: Targets) -> None:
    ipc, dds, split = s1.get("ipc"), s1.get("dds"), s1.get("split")
    name = "S1 ipc zero loss (mcap, default cache)"
    if good(ipc):
        targets.add(name, without_loss(ipc) if default_storage(args) else None,
                    f"lost {ipc['lost']} of {ipc['published']}, drivers at >= {100 * ipc['min_pub_ratio']:.1f} % of "
                    "nominal" + ("" if default_storage(args) else " (not the default storage/cache: not evaluated)"))
    else:
        targets.add(name, None, "not measured")
    name = f"S1 ipc total CPU s/GB <= {S1_CPU_RATIO:g} of dds"
    if good(ipc) and good(dds) and ipc.get("total_cpu_s_per_gb") and dds.get("total_cpu_s_per_gb"):
        a, b = ipc["total_cpu_s_per_gb"], dds["total_cpu_s_per_gb"]
        targets.add(name, a <= S1_CPU_RATIO * b, f"ipc {a:.2f} vs dds {b:.2f} s/GB (ratio {a / b:.2f})")
    else:
        targets.add(name, None, "not measured")
    name = f"S1 split ({args.split_mb:g} MiB files) lossless, write latency p99 <= {SPLIT_P99_RATIO:g}x unsplit"
    a, b = ((e.get("latency_ms") or {}).get("p99") if good(e) else None for e in (split, ipc))
    if a and b:
        targets.add(name, split["lost"] == 0 and a <= SPLIT_P99_RATIO * b,
                    f"lost {split['lost']} of {split['published']}, p99 {a:.1f} vs {b:.1f} ms unsplit "
                    f"(ratio {a / b:.2f}), {split.get('bag_files', '?')} files")
    else:
        targets.add(name, None, "not measured")
    name = f"S1 ipc container peak RSS < max_cache_size + {RSS_MARGIN_MIB} MiB"
    if good(ipc):
        limit = args.cache_mb + RSS_MARGIN_MIB
        targets.add(name, ipc["recorder_rss_mb"] < limit, f"{ipc['recorder_rss_mb']:.0f} MiB vs {limit:.0f} MiB")
    else:
        targets.add(name, None, "not measured")


def s2_targets(s2: Optional[dict[str, Any]], targets: Targets) -> None:
    """Judged on the largest lossless ipc step; below a target they fail only when ipc did lose messages at the
    next step (a ramp capped below the target proves nothing)."""
    name = f"S2 ipc lossless cameras >= {S2_CAMERAS_RATIO}x dds"
    if s2 and "ipc" in s2["largest_lossless"] and "dds" in s2["largest_lossless"]:
        a, b = s2["largest_lossless"]["ipc"], s2["largest_lossless"]["dds"]
        capped = "" if s2["limit_reached"].get("ipc") else f" (ipc capped at {s2['cap']})"
        targets.add(name, a >= max(1, S2_CAMERAS_RATIO * b),
                    f"ipc {a} vs dds {b}{capped}" + (" (no lossless step at all)" if a == 0 else ""))
    else:
        targets.add(name, None, "not measured")
    s2_direct_target(s2, targets)
    name = f"ipc MB/s >= {100 * OVERLOAD_CEILING_SHARE:.0f} % of the ceiling past its lossless limit"
    over = s2.get("ipc_overload") if s2 else None
    if over and s2.get("ceiling"):
        ratio = over["mb_per_s"] / s2["ceiling"]["mb_per_s"]
        targets.add(name, ratio >= OVERLOAD_CEILING_SHARE,
                    f"{over['mb_per_s']:.0f} MB/s at {over['cameras']} cameras vs ceiling "
                    f"{s2['ceiling']['mb_per_s']:.0f} MB/s ({100 * ratio:.0f} %)")
    else:
        targets.add(name, None, "ipc was not driven past its lossless limit" if s2 else "not measured")


def s2_direct_target(s2: Optional[dict[str, Any]], targets: Targets) -> None:
    """ipc lossless with S2_CAMERAS cameras, judged on its largest lossless step, and at >= S2_DIRECT_SHARE_PCT of
    the direct-write limit, judged on its largest lossless step that ended its window with the backlog within
    ``max_cache_size`` (a step that ended it deep in the stall reserve was lossless only for as long as the reserve
    lasts: not a rate the recorder sustains). Below a target they fail only when ipc did lose messages at the
    next step (a ramp capped below proves nothing)."""
    cameras_name = f"S2 ipc lossless with {S2_CAMERAS} cameras"
    name = f"S2 ipc lossless within its cache at >= {S2_DIRECT_SHARE_PCT} % of the direct-write limit"
    steps = [step for step in (s2 or {}).get("steps", []) if step["mode"] == "ipc" and good(step)]
    if not s2 or not steps:
        targets.add(cameras_name, None, "not measured")
        targets.add(name, None, "not measured")
        return
    best = max((step for step in steps if step["lossless"]), key=lambda step: step["cameras"], default=None)
    reached = s2["limit_reached"].get("ipc", False)
    capped = "" if reached else f" (no loss up to the cap of {s2['cap']})"
    count = best["cameras"] if best else 0
    targets.add(cameras_name, True if count >= S2_CAMERAS else (False if reached else None),
                f"largest lossless ipc step: {count} cameras{capped}")
    sustained = max((step for step in steps if step["lossless"] and step.get("within_cache") is not False),
                    key=lambda step: step["cameras"], default=None)
    pct = sustained.get("direct_write_pct") if sustained else 0.0
    if pct is None:
        targets.add(name, None, "no direct-write limit measured (--direct-mb 0)")
        return
    reserve = (f"; {count} cameras lossless but {best['end_backlog_mb']:.0f} MB behind at the end of the window "
               "(in the stall reserve)" if best and sustained is not best else "")
    targets.add(name, True if pct >= S2_DIRECT_SHARE_PCT else (False if reached or reserve else None),
                f"{sustained['mb_per_s'] if sustained else 0:.0f} MB/s at {sustained['cameras'] if sustained else 0} "
                f"cameras = {pct:.0f} % of the direct-write limit{reserve}{capped}")


def s2_repeat_target(repeat: dict[str, Any], args: argparse.Namespace, targets: Targets) -> None:
    """S2's ipc step repeated (--repeat): lossless in every run, with the default storage and cache; each run's
    share of the direct-write limit and peak RSS reported."""
    name = f"S2 ipc lossless with {repeat['cameras']} cameras in {REPEAT_RUNS} of {REPEAT_RUNS} consecutive runs"
    runs = [run for run in repeat["results"] if good(run)]
    detail = (f"lossless in {repeat['lossless_runs']} of {repeat['runs']} runs; % of the direct-write limit per "
              "run: " + ", ".join(fmt(run.get("direct_write_pct"), ".0f") for run in runs)
              + "; recorder peak RSS per run: " + ", ".join(fmt(run["recorder_rss_mb"], ".0f") for run in runs)
              + " MiB")
    if args.repeat < REPEAT_RUNS or not default_storage(args):
        targets.add(name, None, detail + f" (needs --repeat >= {REPEAT_RUNS} and the default storage and cache)")
        return
    targets.add(name, repeat["lossless_runs"] == repeat["runs"], detail)


def s3_targets(s3: dict[str, Any], args: argparse.Namespace, targets: Targets) -> None:
    ipc, dds, baseline = s3.get("ipc"), s3.get("dds"), s3.get("baseline")
    name = f"S3 ipc zero loss, recorder CPU per message <= 1/{1 / S3_RECORDER_RATIO:g} of dds"
    a = ipc.get("recorder_cpu_best_us_per_msg") if good(ipc) else None
    b = dds.get("recorder_cpu_best_us_per_msg") if good(dds) else None
    if a is not None and b:
        how = ("writer thread; the subtraction gave " + fmt(ipc["recorder_cpu_us_per_msg"], ".1f") + " us"
               if ipc.get("recorder_cpu_subtraction_below_writer") else "ipc total - drivers only")
        targets.add(name, without_loss(ipc) and a <= S3_RECORDER_RATIO * b,
                    f"lost {ipc['lost']} of {ipc['published']}, drivers at >= {100 * ipc['min_pub_ratio']:.1f} % "
                    f"of nominal; {a:.1f} ({how}) vs {b:.1f} us/msg (ratio {a / b:.2f})")
    else:
        targets.add(name, None, "not measured")
    name = f"S3 ipc zero loss, drivers + recorder CPU per message <= {S3_BASELINE_RATIO:g} of --baseline"
    if good(ipc) and good(baseline):
        ratio = total_us_per_msg(ipc) / total_us_per_msg(baseline)
        targets.add(name, without_loss(ipc) and ratio <= S3_BASELINE_RATIO,
                    f"{total_us_per_msg(ipc):.1f} vs {total_us_per_msg(baseline):.1f} us/msg at {baseline['code']} "
                    f"(ratio {ratio:.2f}); lost {ipc['lost']} of {ipc['published']}")
    elif args.baseline:
        targets.add(name, None, "not measured")


def repeat_targets(repeat: dict[str, Any], args: argparse.Namespace, targets: Targets) -> None:
    name = f"S1 ipc lossless in {REPEAT_RUNS} of {REPEAT_RUNS} consecutive runs"
    m = repeat["per_mode"].get("ipc")
    if m and args.repeat >= REPEAT_RUNS:
        targets.add(name, m["lossless_runs"] == m["runs"] if default_storage(args) else None,
                    f"lossless in {m['lossless_runs']} of {m['runs']} consecutive runs (all must be); lost % max "
                    f"{fmt(m['lost_pct_max'], '.2f')}" + ("" if default_storage(args) else
                                                          " (not the default storage/cache)"))
    else:
        targets.add(name, None, f"needs ipc and --repeat >= {REPEAT_RUNS}")
    name = f"S1 ipc total CPU per GB <= {REPEAT_CPU_RATIO:g} of dds in every run"
    ratios = repeat["ipc_dds_cpu_per_gb_ratio"]
    if ratios:
        targets.add(name, all(r is not None and r <= REPEAT_CPU_RATIO for r in ratios),
                    "ratio per run: " + ", ".join(fmt(r, ".2f") for r in ratios))
    else:
        targets.add(name, None, "needs ipc and dds")
    m, ratios = repeat["per_mode"].get("split"), repeat["split_ipc_p99_ratio"]
    if m and ratios:
        targets.add(f"S1 split lossless, write latency p99 <= {SPLIT_P99_RATIO:g}x unsplit in every run "
                    f"({m['runs']})",
                    m["lossless_runs"] == m["runs"] and all(r is not None and r <= SPLIT_P99_RATIO for r in ratios),
                    f"split lossless in {m['lossless_runs']} of {m['runs']} runs; p99 ratio per run: "
                    + ", ".join(fmt(r, ".2f") for r in ratios))


#: The parts compared with the previous result of the same rig (benchmarks.record.previous), by target name.
PREVIOUS_TARGETS = {
    "S1": "S1 CPU figures no worse than the previous result of the same rig, beyond the --repeat noise",
    "S4": "S4 lossless camera counts and codec CPU per frame no worse than the previous S4 result of "
          "the same cameras, beyond the noise",
}


def previous_target(report: dict[str, Any], results: Path, targets: Targets, part: str = "S1") -> None:
    """No figure of ``part`` (S1, S4) worse than in the previous result file of the same rig by more than the
    noise (benchmarks.record.previous)."""
    name = PREVIOUS_TARGETS[part]
    if not measured(report, part):
        targets.add(name, None, f"{part} not measured")
        return
    found = find_previous(results, report, part)
    if found is None:
        targets.add(name, None, f"no earlier {part} result of the same rig under {results}")
        return
    path, previous = found
    changes = COMPARE[part](report, previous)
    where = (f"previous: {path.parent.name} (code at {previous.get('git', {}).get('commit', '?')}, "
             f"{previous.get('command', '?')})")
    if machine(report) != machine(previous):
        where += f"; machines differ: {machine(previous)} then, {machine(report)} now"
    if not changes:
        targets.add(name, None, f"no figure in common with the {where}")
        return
    targets.add(name, not any(change.worse for change in changes),
                "; ".join(change.text() for change in changes) + f"; {where}")


def s4_targets(s4: dict[str, Any], targets: Targets) -> None:
    """Per codec of S4_CODEC_TARGETS: bytes against raw (its largest lossless step, else its first), PSNR (its
    run beside raw) and the largest camera count without loss; and raw beside every codec loses nothing."""
    for codec, (raw_pct, min_db, cameras) in S4_CODEC_TARGETS.items():
        name = (f"S4 {codec} at the defaults: <= {raw_pct:g} % of raw bytes at >= {min_db:g} dB, >= {cameras} "
                "camera(s) without loss")
        steps = [s for s in s4["steps"] if s["codec"] == codec and good(s)]
        beside = next((b for b in s4["beside"] if b["codec"] == codec and good(b)), None)
        quality = (beside or {}).get("psnr", {}).get("psnr_db")
        if not steps or quality is None:
            targets.add(name, None, "not measured" if codec in s4["codecs"] else f"{codec} not in --s4-codecs")
            continue
        lossless = [s for s in steps if s["lossless"]]
        step = max(lossless, key=lambda s: s["cameras"]) if lossless else steps[0]
        count = s4["largest_lossless"][codec]
        capped = "" if s4["limit_reached"][codec] else f" (no loss up to the cap of {s4['cap']})"
        enough = count >= cameras or (None if not s4["limit_reached"][codec] else False)
        ok = step["raw_pct"] <= raw_pct and quality >= min_db and enough
        targets.add(name, None if ok is None else bool(ok),
                    f"{step['raw_pct']:.2f} % of raw at {step['cameras']} camera(s), {quality:.1f} dB, largest "
                    f"lossless camera count {count}{capped}")
        s4_limit_target(s4, codec, targets)
    name = "S4 raw recorded beside each encoder loses no frame"
    runs = [b for b in s4["beside"] if good(b)]
    if not runs:
        targets.add(name, None, "not measured")
        return
    failed = [b["codec"] for b in s4["beside"] if not good(b)]
    targets.add(name, not failed and all(b["raw"]["lost"] == 0 and b["raw"]["min_pub_ratio"] >= PUBLISH_RATE_OK
                                         and b["info_lost"] == 0 for b in runs),
                "; ".join(f"beside {b['codec']}: raw lost {b['raw']['lost']} of {b['raw']['published']}, drivers at "
                          f">= {100 * b['raw']['min_pub_ratio']:.1f} % of nominal" for b in runs)
                + (f"; failed: {', '.join(failed)}" if failed else ""))


def s4_limit_target(s4: dict[str, Any], codec: str, targets: Targets) -> None:
    """The largest lossless camera count of ``codec`` at least S4_LIMIT_SHARE of its codec limit in the same run;
    below, a FAIL only when the ramp lost frames above it (a ramp capped below proves nothing)."""
    name = (f"S4 {codec}: lossless cameras (drivers included) >= {S4_LIMIT_SHARE:g} x the codec limit (cores x "
            "frame interval / the codec's CPU per frame)")
    limits = s4.get("limits") or {}
    limit = (limits.get("codecs") or {}).get(codec)
    if codec not in s4["largest_lossless"] or not limit:
        targets.add(name, None, "not measured" if codec in s4["codecs"] else f"{codec} not in --s4-codecs")
        return
    count, cameras = s4["largest_lossless"][codec], limit["cameras"]
    reached = s4["limit_reached"][codec]
    capped = "" if reached else f" (no loss up to the cap of {s4.get('caps', {}).get(codec, s4['cap'])})"
    enough = count >= S4_LIMIT_SHARE * cameras
    targets.add(name, True if enough else (False if reached else None),
                f"{count} camera(s) without loss{capped} = {100 * count / cameras:.0f} % of the codec limit "
                f"{cameras:.2f} ({limits['cores']} cores x {limits['frame_interval_ms']:.1f} ms / "
                f"{limit['ms_per_frame']:.2f} ms {limit['clock']} CPU per frame over {limit['frames']} frames); "
                f"moonshot {S4_MOONSHOT[codec]} camera(s): {'reached' if count >= S4_MOONSHOT[codec] else 'not yet'}")


def evaluate_targets(report: dict[str, Any], args: argparse.Namespace) -> list[dict[str, Any]]:
    targets = Targets()
    s1 = report.get("S1") or {}
    s1_targets(s1, args, targets)
    results = Path(args.results) if args.results else RESULTS
    previous_target(report, results, targets)
    if s1.get("repeat"):
        repeat_targets(s1["repeat"], args, targets)
    s2_targets(report.get("S2"), targets)
    if (report.get("S2") or {}).get("repeat"):
        s2_repeat_target(report["S2"]["repeat"], args, targets)
    s3_targets(report.get("S3") or {}, args, targets)
    if report.get("S4"):
        s4_targets(report["S4"], targets)
        previous_target(report, results, targets, "S4")
    return targets.rows
