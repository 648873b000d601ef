#!/usr/bin/env python3
"""The result tables of the documentation, generated from the benchmarks' result files.

    python -m benchmarks.report [--check] [--results DIR] [--docs FILE ...]

Every result folder (``benchmarks/results/<date>-<commit>/``) with JSON files gets its ``README.md``: the tables
of its own JSON. In the documentation (README.md and docs/*.md by default), whatever stands between the lines
``<!-- BEGIN GENERATED: NAME -->`` and ``<!-- END GENERATED: NAME -->`` is replaced by the table NAME (see
``TABLES``) made from the newest result file that holds what it needs; nothing else in a file changes.
A block whose table no result file can give is left as it is, with a message saying what run would give it.

``--check`` changes nothing: it prints every difference and exits 1 if there is one, so that the tables in the
documentation are never typed by hand.
"""
from __future__ import annotations

import argparse
import difflib
import json
import os
import re
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

REPO = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):  # run as a script: benchmarks.* from this checkout
    sys.path.insert(1, str(REPO))

from benchmarks.locations import RESULTS  # noqa: E402
from benchmarks.record.report import fmt, s4_steps, search_text  # noqa: E402

BLOCK = re.compile(r"^<!-- BEGIN GENERATED: (?P<name>[\w.-]+) -->\n(?P<body>.*?)^<!-- END GENERATED: (?P=name) -->$",
                   re.MULTILINE | re.DOTALL)
FOLDER_TABLES = "README.md"
NUMBER_WORDS = "no one two three four five six seven eight nine".split()


class Missing(Exception):
    """A result file lacks what a table needs."""


# ----------------------------------------------------------------------------------------------- tables
def markdown(headers: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers),
            *("| " + " | ".join(row) + " |" for row in rows)]


def part(record: dict[str, Any], key: str) -> dict[str, Any]:
    if not record.get(key):
        raise Missing(f"no {key} in this run")
    return record[key]


def measured(entry: Optional[dict[str, Any]]) -> bool:
    return entry is not None and "error" not in entry


def lost_text(entry: dict[str, Any]) -> str:
    return f"{entry['lost']}" + (f" ({entry['lost_pct']:.1f} %)" if entry["lost"] else "")


def rss_text(entry: dict[str, Any]) -> str:
    return " + ".join(f"{v:.0f}" for v in (entry.get("peak_rss_mb") or {}).values()) + " MiB"


def s1_table(record: dict[str, Any]) -> list[str]:
    s1 = part(record, "S1")
    split_mb = record["config"]["split_mb"]
    rows = []
    for mode, label in (("ipc", "ipc"), ("split", f"split ({split_mb:g} MiB files)"), ("dds", "dds")):
        e = s1.get(mode)
        if e is None:
            continue
        if not measured(e):
            rows.append([label, f"failed: {e['error'][:80]}"] + [""] * 7)
            continue
        lat = e.get("latency_ms") or {}
        rows.append([label, str(e["published"]), str(e["recorded"]), f"{e['lost_pct']:.2f} %", fmt(e["mb_per_s"]),
                     fmt(e["total_cpu_s"], ".2f"), fmt(e.get("total_cpu_s_per_gb"), ".2f"),
                     fmt(e.get("recorder_cpu_s_per_gb"), ".2f"), rss_text(e),
                     f"{fmt(lat.get('p50'))} / {fmt(lat.get('p99'))} ms"])
    if measured(s1.get("drivers")):
        rows.append(["drivers only", "", "", "", "", fmt(s1["drivers"]["total_cpu_s"], ".2f"), "", "",
                     rss_text(s1["drivers"]), ""])
    if measured(s1.get("ceiling")):
        c = s1["ceiling"]
        rows.append(["ceiling (buffered)", "", "", "", fmt(c["mb_per_s"]), fmt(c["total_cpu_s"], ".2f"),
                     fmt(c["total_cpu_s_per_gb"], ".2f"), "", "", ""])
    if not rows:
        raise Missing("no S1 mode measured")
    if measured(record.get("direct_write")):
        d = record["direct_write"]
        rows.append(["direct-write limit (O_DIRECT)", "", "", "", fmt(d["mb_per_s"]), "", fmt(d["cpu_s_per_gb"], ".2f"),
                     "", "", ""])
    return markdown(["mode", "published", "recorded", "lost", "MB/s", "total CPU s", "CPU s per GB",
                     "recorder's own CPU s per GB", "peak RSS", "receive-to-write p50 / p99"], rows)


def s2_table(record: dict[str, Any]) -> list[str]:
    s2 = part(record, "S2")
    rows = []
    for step in s2["steps"]:
        if not measured(step):
            rows.append([step["mode"], str(step["cameras"]), f"failed: {step['error'][:80]}", "", "", "", "", "",
                         "no"])
            continue
        direct = step.get("direct_write_pct")
        rows.append([step["mode"], str(step["cameras"]), lost_text(step), fmt(step["mb_per_s"]),
                     "" if direct is None else f"{direct:.0f} %", fmt(step.get("recorder_rss_mb"), ".0f"),
                     backlog_text(step), fmt(step["total_cpu_s"], ".2f"), "yes" if step["lossless"] else "no"])
    return markdown(["mode", "cameras", "lost", "MB/s", "of direct-write limit", "recorder peak RSS MiB",
                     "backlog MB: peak, end of window", f"total CPU s per {s2['seconds']:g} s", "lossless"], rows)


def backlog_text(step: dict[str, Any]) -> str:
    """The recorder's peak backlog and its backlog at the end of the window, marked when that was beyond the cache
    (in the stall reserve); empty in runs that did not record them."""
    peak, end = step.get("peak_backlog_mb"), step.get("end_backlog_mb")
    if peak is None or end is None:
        return ""
    return f"{peak:.0f}, {end:.0f}" + ("" if step.get("within_cache") else " (stall reserve)")


def s2_repeat_table(record: dict[str, Any]) -> list[str]:
    repeat = part(record, "S2").get("repeat")
    if not repeat:
        raise Missing("no S2 --repeat in this run")
    rows = []
    for number, run in enumerate(repeat["results"], 1):
        if not measured(run):
            rows.append([str(number), f"failed: {run['error'][:80]}", "", "", "", ""])
            continue
        direct = run.get("direct_write_pct")
        rows.append([str(number), lost_text(run), fmt(run["mb_per_s"]), "" if direct is None else f"{direct:.0f} %",
                     fmt(run.get("recorder_rss_mb"), ".0f"), "yes" if run["lossless"] else "no"])
    direct = record.get("direct_write") or {}
    s2_targets = [f"* {t['result']}: {t['target']}: {t['detail']}." for t in record.get("targets", [])
                  if t["target"].startswith("S2")]
    return [*markdown(["run", "lost", "MB/s", "of direct-write limit", "recorder peak RSS MiB", "lossless"], rows), "",
            f"ipc with {repeat['cameras']} {record['config']['height']}p{record['config']['fps']:g} cameras "
            f"({record['S2']['base']}), {record['S2']['seconds']:g} s "
            f"windows: lossless in {repeat['lossless_runs']} of {repeat['runs']} runs; direct-write limit of the run "
            f"{fmt(direct.get('mb_per_s'), '.0f')} MB/s. The S2 targets of the same run (its ramp and these runs):",
            "", *s2_targets]


def micro(value: Optional[float]) -> str:
    return "" if value is None else f"{value:.1f} µs"


def s3_table(record: dict[str, Any]) -> list[str]:
    s3 = part(record, "S3")
    rows = []
    for mode in ("ipc", "dds"):
        e = s3.get(mode)
        if e is None:
            continue
        if not measured(e):
            rows.append([mode, f"failed: {e['error'][:80]}", "", "", "", ""])
            continue
        reliable = not e.get("recorder_cpu_subtraction_below_writer")
        rows.append([mode, str(e["published"]), str(e["recorded"]), str(e["lost"]),
                     micro(e.get("writer_thread_us_per_msg")),
                     micro(e.get("recorder_cpu_us_per_msg") if reliable else None)])
    if not rows:
        raise Missing("no S3 recorder mode measured")
    return markdown(["mode", "published", "recorded", "lost", "writer thread per message",
                     "recorder CPU per message"], rows)


def s4_limits_table(s4: dict[str, Any]) -> list[str]:
    """Per compressed codec, its codec limit and its ramp's share of it (runs that measured limits)."""
    limits = s4.get("limits") or {}
    if not limits.get("codecs"):
        return [] if "limits" not in s4 else ["", f"Codec limits: failed: {limits.get('error', 'none measured')}"]
    rows = [[label, f"{limit['ms_per_frame']:.2f} ms ({limit['clock']})",
             f"{limit['cold_ms_per_frame']:.2f} ms" if "cold_ms_per_frame" in limit else "-",
             f"{limit['cameras']:.2f}", str(s4["largest_lossless"].get(label, 0)),
             f"{100 * s4['largest_lossless'].get(label, 0) / limit['cameras']:.0f} %"]
            for label, limit in limits["codecs"].items()]
    return ["", *markdown(["codec", "CPU per frame, codec alone", "the same, frame out of the caches",
                           "codec limit (cameras)", "cameras without loss", "of the limit"], rows), "",
            f"Codec limit: {limits['cores']} cores x {limits['frame_interval_ms']:.1f} ms frame interval / the CPU "
            f"time one frame costs the codec alone (colour conversion and encoding through "
            f"`components/image_encoder/codecs.py`, {limits['frames']} photo frames, `time.thread_time`; the "
            "process's CPU time for an encoder with threads of its own), measured in the same run. Beside it, the "
            "same with each frame pushed out of the caches before it is encoded, as a frame waiting among several "
            "cameras' frames is (benchmarks/record/codec_limit.py; not in the limit)."]


def s4_ramp_text(s4: dict[str, Any]) -> str:
    """How the run's ramps chose their camera counts: searched, or doubled (results before the search)."""
    if s4.get("ramp") == "search":
        return search_text(s4)
    return f"1, 2, 4 ... cameras per codec until a frame is lost (cap {s4['cap']})"


def s4_table(record: dict[str, Any]) -> list[str]:
    """S4: each codec's ramp and its run beside raw, its codec limits, then S4's targets."""
    s4, config = part(record, "S4"), record["config"]
    rows = []
    for step in [*s4_steps(s4), *s4["beside"]]:
        label = f"{step['codec']}" + (" + raw" if step.get("beside") else "")
        if not measured(step):
            rows.append([label, str(step["cameras"]), f"failed: {step['error'][:80]}"] + [""] * 7)
            continue
        lat = step.get("latency_ms") or {}
        beside = f"raw lost {step['raw']['lost']} of {step['raw']['published']}" if step.get("beside") else ""
        rows.append([label, str(step["cameras"]), f"{step['lost']} of {step['published']}",
                     fmt(step["mb_per_s"], ".2f"),
                     f"{fmt(step['raw_pct'], '.2f')} %", fmt((step.get("psnr") or {}).get("psnr_db")),
                     fmt(step["cpu_per_camera"], ".2f"), f"{fmt(lat.get('p50'))} / {fmt(lat.get('p99'))} ms",
                     fmt(step["hours_per_tb"], ".1f"), beside or ("yes" if step["lossless"] else "no")])
    targets = [f"* {t['result']}: {t['target']}: {t['detail']}." for t in record.get("targets", [])
               if t["target"].startswith("S4")]
    return [*markdown(["codec", "cameras", "frames lost", "MB/s", "of raw", "PSNR dB", "CPU cores per camera",
                       "receive-to-write p50 / p99", "hours per TB", "lossless"], rows), *s4_limits_table(s4), "",
            f"{config['width']}x{config['height']} rgb8 cameras at {config['fps']:g} Hz with photo content, "
            f"{s4['seconds']:g} s windows, drivers, encoder and recorder in one container; {s4_ramp_text(s4)}. "
            "Targets of the same run:", "", *targets]


def s4_sizing_table(record: dict[str, Any]) -> list[str]:
    """What one 1080p30 camera costs per codec (S4's largest lossless step of each)."""
    sizing = part(record, "S4").get("sizing")
    if not sizing:
        raise Missing("no codec of S4 recorded a camera without loss")
    rows = [[codec, fmt(c["cpu_per_camera"], ".2f"), fmt(c["mb_per_s_per_camera"], ".2f"),
             f"{fmt(c['raw_pct'], '.2f')} %",
             fmt(c.get("psnr_db")), f"{c['hours_per_tb_per_camera']:,.0f}",
             f"{c['largest_lossless']}" + ("" if c["limit_reached"] else "+")] for codec, c in sizing.items()]
    return markdown(["codec", "CPU cores per camera", "MB/s per camera", "of raw", "PSNR dB", "hours per TB",
                     "cameras without loss (this machine)"], rows)


def targets_table(record: dict[str, Any]) -> list[str]:
    rows = [[t["target"], f"{t['result']}: {t['detail']}"] for t in part(record, "targets")]
    return markdown(["target", "result"], rows)


def full_run_targets_table(record: dict[str, Any]) -> list[str]:
    """The targets of a run of every scenario (a run of a part of them leaves most of them N/A)."""
    if not all(record.get(key) for key in ("S1", "S2", "S3")):
        raise Missing("not a run of S1, S2 and S3")
    return targets_table(record)


def headline_table(record: dict[str, Any]) -> list[str]:
    s1, s2 = part(record, "S1"), part(record, "S2")
    ipc, dds = s1.get("ipc"), s1.get("dds")
    if not measured(ipc) or not measured(dds):
        raise Missing("S1 lacks ipc or dds")
    scenario = s1["scenario"]

    def lost(e: dict[str, Any]) -> str:
        return f"{e['lost']} of {e['published']}" + (f" ({e['lost_pct']:.2f} %)" if e["lost"] else "")

    def cameras(mode: str) -> str:
        """The largest lossless step; and, where the recorder ended a larger lossless step behind (in its stall
        reserve), the largest it sustained."""
        capped = "" if s2["limit_reached"].get(mode) else f" (no loss up to the ramp's cap of {s2['cap']})"
        best = s2["largest_lossless"].get(mode, "-")
        sustained = [step["cameras"] for step in s2["steps"] if step["mode"] == mode and measured(step)
                     and step["lossless"] and step.get("within_cache") is not False]
        behind = (f"; {max(sustained, default=0)} with the writer caught up at the end of the window"
                  if best != "-" and max(sustained, default=0) != best else "")
        return f"{best}{capped}{behind}"

    config = record["config"]
    camera = f"{config['height']}p{config['fps']:g}"
    count = NUMBER_WORDS[scenario["cameras"]] if scenario["cameras"] < len(NUMBER_WORDS) else scenario["cameras"]
    return markdown([f"S1 rig: {count} {camera} cameras, a LiDAR, an IMU; {scenario['nominal_mb_per_s']:.0f} MB/s "
                     f"for {scenario['seconds']:g} s", "recorder in the drivers' container (intra-process)",
                     "recorder in its own process (DDS)"],
                    [["messages lost", lost(ipc), lost(dds)],
                     ["CPU per GB recorded", *(f"{fmt(e.get('total_cpu_s_per_gb'), '.2f')} s" for e in (ipc, dds))],
                     ["of which the recorder's own (what it costs beside your drivers)",
                      *(f"{fmt(e.get('recorder_cpu_s_per_gb'), '.2f')} s" for e in (ipc, dds))],
                     ["receive-to-write latency p99",
                      *(f"{fmt((e.get('latency_ms') or {}).get('p99'))} ms" for e in (ipc, dds))],
                     [f"{camera} cameras recorded without loss (S2 ramp)", cameras("ipc"), cameras("dds")]])


def highest_rate(result: dict[str, Any]) -> str:
    """The highest sustained rate, and why the next one was not."""
    runs = result["runs"]
    best = result["highest_sustained_rate"]
    last = runs[-1] if runs else None
    if last is None or last.get("sustained"):
        return f"{fmt(best, 'g', 'none')}x (every rate tried)"
    if "error" in last:
        why = f"failed: {last['error'][:60]}"
    else:
        missing = last["expected"] - last["delivered"]
        why = (f"{missing} lost, " if missing else "") + f"wall {last['wall_s'] / last['ideal_s']:.2f}x ideal"
    return (f"{best:g}x" if best else "none") + f" ({last['rate']:g}x: {why})"


def replay_table(replay: dict[str, Any]) -> list[str]:
    rows = []
    for mode, result in replay.get("modes", {}).items():
        if not measured(result):
            rows.append([mode, f"failed: {result['error'][:80]}", "", "", "", ""])
            continue
        one = next((r for r in result["runs"] if r["rate"] == 1.0 and "error" not in r), None)
        err = one["publish_error_ms"] if one else {}
        rows.append([mode, highest_rate(result), f"{one['delivered']} / {one['expected']}" if one else "",
                     fmt(one["wall_s"] / one["ideal_s"], ".3f") if one else "",
                     f"{fmt(err.get('p50'), '.2f')} / {fmt(err.get('p99'), '.2f')} / {fmt(err.get('max'), '.1f')} ms"
                     if one else "", " + ".join(f"{v:.1f}" for v in one["cpu_s"].values()) if one else ""])
    if not rows:
        raise Missing("no replay mode measured")
    target = replay["target"]
    return [*markdown(["mode", "highest sustained rate", "rate 1: delivered", "wall / ideal",
                       "publish error p50 / p99 / max", "CPU s"], rows),
            "", f"Target ({target['target']}): {target['result']}; {target['detail']}."]


CODEC_NAMES = {"h264": "H.264", "jpeg": "JPEG"}


def decode_replay_table(decode: dict[str, Any]) -> list[str]:
    """Per scenario: the baseline's figure -> this code's (one of them when the run had no baseline)."""
    summary = part(decode, "summary")
    rows = []
    for scenario, by_code in summary.items():
        def pair(key: str, spec: str) -> str:
            return " → ".join(fmt(by_code[code][key], spec) for code in ("baseline", "current") if code in by_code)

        current, baseline = by_code["current"], by_code.get("baseline")
        ratio = (f"{current['fast_speed'] / baseline['fast_speed']:.2f}x"
                 if baseline and baseline["fast_speed"] and current["fast_speed"] else "")
        rows.append([" + ".join(f"{n} {CODEC_NAMES[codec]}" for codec, n in decode["bags"][scenario]["streams"].items()),
                     pair("speed", ".3f"), pair("lag_s", ".2f"), pair("wall_s", ".2f"), pair("cores", ".2f"),
                     pair("fast_speed", ".2f"),
                     ratio, pair("fast_cores", ".2f"), pair("cpu_ms_per_frame", ".1f"),
                     " / ".join("yes" if by_code[code]["complete"] else "NO" for code in by_code)])
    target, environment = decode["target"], decode["environment"]
    baseline = decode["codes"].get("baseline")
    code = f"the baseline ({baseline}) → this code" if baseline else "this code"
    runs = [run for by_code in decode["runs"].values() for runs in by_code.values() for run in runs if "error" not in run]
    loads = sorted(run["loadavg"] for run in runs)
    others = statistics.median(run["other_cpu_s"] / run["wall_s"] for run in runs)
    return [*markdown(["1080p30 streams", "rate 1: speed", "lag s", "wall s", "cores", "fastest: x real time",
                       "fastest: this / baseline", "cores", "CPU ms per frame", "every frame decoded"], rows),
            "", f"Each figure: {code}, median of {decode['config']['repeat']} run(s) each; the fastest runs at rate "
                f"{decode['config']['fast_rate']:g}. {decode['bags'][next(iter(summary))]['span_s']:.1f} s bags. "
                f"{environment['cpus']} CPUs shared with other work: load average {loads[0]:.1f} to {loads[-1]:.1f} "
                f"at the runs' ends, other processes using {others:.2f} cores (median over the runs). Target "
                f"({target['target']}): {target['result']}; {target['detail']}."]


def recover_table(recover: dict[str, Any]) -> list[str]:
    if "in_place" not in recover:
        raise Missing("no recover run measured")
    rows = [[mode.replace("_", " "), f"{recover[mode]['mb_per_s']:.0f}", f"{recover[mode]['disk_read_mb_per_s']:.0f}",
             f"{recover[mode]['share_of_read_speed']:.0%}", f"{recover[mode]['extra_bytes'] / 1e6:.1f}",
             str(recover[mode]["messages"])] for mode in ("in_place", "copy")]
    target = recover["target"]
    return [*markdown(["mode", "recover MB/s", "cold read MB/s", "share", "extra space MB", "messages kept"], rows),
            "", f"A {recover['bag_bytes'] / 1e9:.1f} GB bag cut inside its last chunk. Target ({target['target']}): "
                f"{target['result']}; {target['detail']}."]


def fleet_table(fleet: dict[str, Any]) -> list[str]:
    if "central" not in fleet:
        raise Missing("no fleet run measured")
    rows = []
    for mode in ("fleet", "central"):
        topics = [t for bag in fleet[mode]["bags"] for t in bag["topics"].values()]
        rows.append([mode, f"{fleet[mode]['cpu_total_per_s']:.2f}", str(sum(t["frames"] for t in topics)),
                     str(sum(t["gaps"] for t in topics)),
                     f"{max(t['start_cut_ms'] for t in topics):.1f}", f"{max(t['stop_cut_ms'] for t in topics):.1f}"])
    return [*markdown(["mode", "CPU s/s (all containers)", "frames", "lost (gaps)", "max start cut ms",
                       "max stop cut ms"], rows),
            "", f"{fleet['hosts']} hosts (network namespaces) x {fleet['cameras_per_host']} cameras "
                f"({fleet['camera']}, {fleet['mb_per_s_per_camera']:.0f} MB/s each), {fleet['seconds']:g} s measured. "
                f"fleet: a local-only recorder per host; central: one recorder on another host, over DDS. "
                f"Fleet CPU / central CPU: {fleet['cpu_ratio_fleet_to_central']:.2f}. A cut is the time from the "
                f"scheduled start to the first frame received (from the last frame to the stop)."]


def merge_table(merge: dict[str, Any]) -> list[str]:
    workloads = part(merge, "workloads")
    rows = [[name, str(entry["inputs"]), f"{entry['payload_bytes'] / 1e6:.0f}", str(entry["messages"]),
             f"{entry['read']['mb_per_s']:.0f}", f"{entry['merge']['mb_per_s']:.0f}", f"{entry['share_of_read']:.0%}",
             f"{entry['merge']['messages_per_s']:.0f}"] for name, entry in workloads.items()]
    return markdown(["workload", "inputs", "payload MB", "messages", "read alone MB/s", "merge MB/s",
                     "merge / read", "merge messages/s"], rows)


FOXGLOVE_MODES = {"no_viewer": "recording, no viewer", "in_container": "viewer through the in-container bridge",
                  "out_of_process": "viewer through a bridge process over DDS",
                  "stalled": "in-container bridge, plus a second client stalled",
                  "video": "viewer of the video channels (H.264, 640 px, 10 Hz) through the in-container bridge"}


def convert_table(convert: dict[str, Any]) -> list[str]:
    bag = part(convert, "bag")
    rows = [[name, f"{statistics.median(bag[name]['seconds']):.2f}",
             f"{bag[name]['mb_per_s']:.0f}", f"{bag[name].get('messages', bag['messages'])}",
             f"{bag['convert']['share_of_read']:.0%} of read" if name == "convert"
             else f"{bag[name]['share_of_convert']:.0%} of convert" if name.startswith("cut") else ""]
            for name in ("read", "convert", "cut_input", "cut_output")]
    return markdown([f"pass ({bag['payload_bytes'] / 1e6:.0f} MB, {bag['messages']} messages)", "median s",
                     "MB/s of the whole bag", "messages written", "share"], rows)


def drop_reasons(run: dict[str, Any]) -> str:
    totals: dict[str, int] = {}
    for reasons in run.get("recorder_drop_reasons", {}).values():
        for reason, count in reasons.items():
            totals[reason] = totals.get(reason, 0) + count
    return ", ".join(f"{reason} {count}" for reason, count in sorted(totals.items())) or "none"


def foxglove_table(foxglove: dict[str, Any]) -> list[str]:
    modes = [mode for mode in FOXGLOVE_MODES if mode in foxglove]
    if "in_container" not in modes:
        raise Missing("no in_container run measured")
    rows = []
    for mode in modes:
        run = foxglove[mode]
        cpu = run["cpu_per_s"]
        watcher = run["viewers"][0] if run["viewers"] else {}
        rows.append([FOXGLOVE_MODES[mode], f"{cpu['container']:.2f}",
                     f"{cpu['bridge_process']:.2f}" if "bridge_process" in cpu else "",
                     " / ".join(f"{camera['fps']:.1f}" for camera in watcher.values()),
                     str(sum(camera["gaps"] for camera in watcher.values())) if watcher else "",
                     str(sum(c["dropped"] for c in run["bridge"].values())) if "bridge" in run else "",
                     str(sum(t["dropped"] + t["queue_dropped"] for t in run["recorder"].values())),
                     str(sum(t["received"] for t in run["recorder"].values())), drop_reasons(run)])
    lines = markdown(["S1 rig recording", "rig container CPU s/s", "bridge process CPU s/s",
                      "viewer fps (front / rear)", "viewer gaps", "bridge queue drops", "recorder drops",
                      "recorder messages",
                      "recorder drops by reason (whole run)"], rows)
    stalled = foxglove.get("stalled", {}).get("stalled")
    note = (f"Windows of {foxglove['seconds']:g} s; load average {foxglove['load_before']:.1f} before the run and "
            f"{foxglove['load_after']:.1f} after it on this 2-core machine, shared with other work.")
    if stalled:
        note += (" The stalled client (SIGSTOP for the whole window): the bridge handed "
                 + ", ".join(f"{t['handed_to_outbox']} frames of {topic.split('/')[1]}" for topic, t in stalled.items())
                 + " to its outbox, it got " + " and ".join(str(t["received"]) for t in stalled.values())
                 + f"; the bridge's own queues dropped {sum(t['bridge_dropped'] for t in stalled.values())}.")
    return [*lines, "", note]


def files_read(files: dict[str, Any]) -> str:
    """How the soak's files were read (benchmarks/endurance/bag_files.py)."""
    indexed = files.get("read_through_indexes", 0)
    if indexed:
        return (f"every message's number read, of {indexed} of the {files['count']} files through their MCAP "
                "message indexes (baglib and rosbags checked their counts), of the others by baglib and rosbags "
                f"reading every message")
    return (f"baglib read every message, rosbags {files['rosbags_read_messages']} one by one and every file's "
            "index")


def soak_table(soak: dict[str, Any]) -> list[str]:
    if "verdicts" not in soak:
        raise Missing("no soak run")
    plan, churn, files, accounting = soak["plan"], soak["churn"], soak["files"], soak["accounting"]
    resources, machine = soak["resources"], soak["machine"]
    accounted = (sum(e.get("recorded", 0) for e in accounting["rig"].values())
                 + accounting["extra"]["recorded_messages"] + accounting["/soak_replay/chatter"]["recorded"])
    rows = [["run", f"{churn['seconds'] / 60:.0f} min: {plan['rig']['describe'].split(';')[0]}; an extra camera "
                    f"loaded every {plan['extra_period_s']:g} s for {plan['extra_alive_s']:g} s, a new recorder "
                    f"every {plan['handover_period_s']:g} s, splits every {plan['split_s']:g} s, a player looping"],
            ["churn", f"{churn['extra_instances']} extra drivers, {churn['recorders']} recorders, {files['count']} "
                      f"files ({files['bytes'] / 1e9:.0f} GB, {files['messages']} messages)"],
            ["sequence numbers accounted for", f"{accounted} (camera infos and hand-over duplicates not counted); "
                                               f"missing: {accounting['lost']}"],
            ["drops reported", f"{sum(bag['dropped'] for bag in soak['bags'])} dropped, "
                               f"{sum(len(bag['lost_events']) for bag in soak['bags'])} messages_lost events"],
            ["bags", f"{sum(1 for bag in soak['bags'] if not bag['problems'])} of {len(soak['bags'])} finalized and "
                     f"matching their recorders' counts; " + files_read(files)
                     + (f"; the reader stood aside {files['reader_pauses']} times ({files['reader_paused_s']:.0f} s) "
                        "while the recorder was behind" if "reader_pauses" in files else "")]]
    for metric, label, unit in (("rss_mib", "RSS", "MiB"), ("fds", "open fds", ""), ("threads", "threads", "")):
        m = resources.get(metric)
        if m:
            unit = f" {unit}" if unit else ""
            rows.append([f"{label} after the warm-up", f"{m['start']:.0f} → {m['end']:.0f}{unit}, slope "
                                                      f"{m['slope_per_hour']:+.1f}{unit}/h"])
    rows.append(["machine", f"container {soak['container']['cpus']:.2f} CPUs, reading the files "
                            f"{files['worker_cpu_s'] / max(churn['seconds'], 1):.2f}, other processes "
                            f"{machine['other_cpus']:.2f}; load average {soak['environment']['loadavg_start'][0]:.1f}"
                            f" → {soak['environment']['loadavg_end'][0]:.1f}"])
    return [*markdown(["figure", "value"], rows), "",
            *markdown(["bound", "result"], [[v["bound"], f"{v['result']}: {v['detail']}"] for v in soak["verdicts"]])]


def fuzz_table(fuzz: dict[str, Any]) -> list[str]:
    if not fuzz.get("seeds"):
        raise Missing("no fuzz seed run")
    rows = []
    for seed in fuzz["seeds"]:
        rss, rates = seed["rss"], seed["rates"]
        late = sum(seed["late"].get(kind, 0) + seed["abandoned"].get(kind, 0) for kind in ("load", "unload"))
        rows.append([str(seed["seed"]), f"{seed['requests']} ({seed['requests'] / max(seed['seconds'], 1e-9):.0f}/s)",
                     f"{late} late or unanswered, slowest {max(seed['slowest_s'].values(), default=0):.2f} s",
                     f"{'alive' if seed['exit_status'] == 0 else 'FAILED'}, exit {seed['exit_status']}",
                     ", ".join(f"{rate:.1f}/s" for rate in rates.values()),
                     f"{rss['start_mib']:.0f} → {rss['last_third_start_mib']:.0f} → {rss['end_mib']:.0f}",
                     f"{rss['growth_last_third_mib']:+.1f} MiB ({rss['slope_last_third_mib_per_10k']:+.2f} per 10 k)",
                     "PASS" if seed["healthy"] else "FAIL: " + ", ".join(k for k, ok in seed["checks"].items()
                                                                          if not ok)])
    return markdown(["seed", "requests", "LoadNode / UnloadNode within 5 s", "container", "drivers afterwards",
                     "RSS MiB: start → 2/3 → end", "RSS over the last third", "result"], rows)


def pixel_formats_table(run: dict[str, Any]) -> list[str]:
    pairs = part(run, "pairs")
    rgb = {pair["codec"]: pair["cpu_ms"] for pair in pairs if pair["encoding"] == "rgb8"}
    rows = [[pair["encoding"], pair["codec"], f"{pair['cpu_ms']:.1f}", f"{pair['caller_ms']:.1f}",
             f"{pair['cpu_ms'] / rgb[pair['codec']]:.2f}" if pair["codec"] in rgb and pair["content"] == "photo"
             else "-",
             f"{pair['kb_per_frame']:,.0f}", f"{pair['raw_pct']:.2f} %"] for pair in pairs]
    environment = run["environment"]
    return [*markdown(["camera encoding", "codec", "CPU ms per frame", "of it on the calling thread",
                       "against rgb8", "KB per frame", "of the camera's bytes"], rows), "",
            f"{run['frames']} frames of {run['size']} per pair, the pairs interleaved in one run, on "
            f"{environment['cpus']} CPUs shared with other work (load average {environment['loadavg_start'][0]:.1f}"
            f" at the start, {environment['loadavg_end'][0]:.1f} at the end)."]


def upload_table(upload: dict[str, Any]) -> list[str]:
    """Ours against boto3's upload_file (medians over the rounds), then S1 with upload on and off."""
    lines: list[str] = []
    if "throughput" in upload:
        t = upload["throughput"]
        rows = [[client, f"{m['mb_per_s']:.0f}", f"{m['mb_per_s'] / t['median']['boto3']['mb_per_s']:.0%}",
                 f"{m['cpu_s_per_gb']:.2f}", f"{m['server_cpu_s_per_gb']:.2f}", f"{m['other_cpus']:.2f}"]
                for client, m in t["median"].items()]
        lines += [*markdown(["client", "MB/s", "of boto3", "client CPU s per GB", "server CPU s per GB",
                             "other processes, CPUs"], rows), "",
                  f"{len(t['bag']['files'])} files, {t['bag']['bytes'] / 1e6:.0f} MB, uploaded "
                  f"{len(t['runs']) // 2} times by each client in alternation to nanio on loopback; medians. Ours "
                  f"/ boto3 per round: {', '.join(f'{r:.0%}' for r in t['round_ratios'])}. Target "
                  f"({t['target']['target']}): {t['target']['result']}; {t['target']['detail']}.", ""]
    if "S1" in upload:
        s1 = upload["S1"]
        rows = []
        for mode in ("upload_off", "upload_on"):
            e = s1[mode]
            if not measured(e):
                rows.append([mode.replace("_", " "), f"failed: {e['error'][:80]}"] + [""] * 7)
                continue
            up = e.get("upload", {})
            rows.append([mode.replace("_", " "), f"{e['published']} ({e['min_pub_ratio']:.1%})", lost_text(e),
                         fmt(e["mb_per_s"]), fmt(e.get("total_cpu_s_per_gb"), ".2f"),
                         fmt(e.get("recorder_cpu_s_per_gb"), ".2f"),
                         fmt(up.get("cpu_s_per_gb"), ".2f"), fmt(up.get("server_cpu_s_per_gb"), ".2f"),
                         fmt(up.get("mb_per_s"), ".0f")])
        lines += [*markdown(["S1", "published (lowest topic's share of nominal)", "lost", "recorded MB/s",
                             "container CPU s per GB", "recorder's own CPU s per GB",
                             "upload process CPU s per GB uploaded", "server CPU s per GB", "upload MB/s"], rows), "",
                  f"{s1['scenario']['describe']}; files of {s1['split_mb']:g} MiB, each uploaded as it is closed "
                  f"(upload.max_rate 0). Target ({s1['target']['target']}): {s1['target']['result']}; "
                  f"{s1['target']['detail']}."]
    if not lines:
        raise Missing("no upload run measured")
    return lines


def cli_latency_table(run: dict[str, Any]) -> list[str]:
    commands = part(run, "commands")
    rows = [[f"`{name}`", " / ".join(f"{value:.2f}" for value in (min(entry["seconds"]),
                                                                   statistics.median(entry["seconds"]),
                                                                   max(entry["seconds"])))]
            for name, entry in commands.items()]
    environment = run["environment"]
    return [*markdown(["command", "min / median / max s"], rows), "",
            f"{run['runs']} runs of each against a running container `{run['container']}`, on "
            f"{environment['cpus']} CPUs (load average {environment['loadavg_start'][0]:.1f} at the start, "
            f"{run['loadavg_end'][0]:.1f} at the end)."]


@dataclass
class Table:
    source: str   # the result file it is made from: record or replay (.json)
    needs: str    # what that file must hold, for the message when none does
    command: str  # a run that gives it
    make: Callable[[dict[str, Any]], list[str]]
    title: str    # its heading in a result folder's README.md


TABLES: dict[str, Table] = {
    "headline": Table("record", "S1 (ipc and dds) and S2 of one run", "make bench", headline_table, ""),
    "s1": Table("record", "S1", "python benchmarks/record_bench.py --quick", s1_table, "S1 rig"),
    "s2": Table("record", "S2", "python benchmarks/record_bench.py --scenarios s2", s2_table, "S2 ramp"),
    "s2_repeat": Table("record", "S2 with --repeat", "python benchmarks/record_bench.py --scenarios s2 --repeat 5",
                       s2_repeat_table, "S2 repeated"),
    "s3": Table("record", "S3", "python benchmarks/record_bench.py --scenarios s3", s3_table, "S3 IMU storm"),
    "s4": Table("record", "S4", "python benchmarks/record_bench.py --scenarios s4", s4_table,
                "S4 compressed recording"),
    "s4_sizing": Table("record", "S4", "python benchmarks/record_bench.py --scenarios s4", s4_sizing_table,
                       "S4: one 1080p30 camera per codec"),
    "targets": Table("record", "targets of S1, S2 and S3", "make bench", full_run_targets_table, ""),
    "run_targets": Table("record", "targets", "python benchmarks/record_bench.py --quick", targets_table, "Targets"),
    "replay": Table("replay", "modes", "python benchmarks/replay_bench.py --quick", replay_table, "Replay"),
    "decode_replay": Table("decode_replay", "summary",
                           "python benchmarks/decode_replay_bench.py --baseline REV", decode_replay_table,
                           "Decoded replay"),
    "recover": Table("recover", "in_place", "python benchmarks/recover_bench.py", recover_table, "Recover"),
    "fleet": Table("fleet", "central", "python benchmarks/fleet_bench.py", fleet_table, "Fleet"),
    "merge": Table("merge", "workloads", "python benchmarks/merge_bench.py", merge_table, "Merge"),
    "convert": Table("convert", "bag", "python benchmarks/convert_bench.py", convert_table, "Convert"),
    "foxglove": Table("foxglove", "in_container", "python benchmarks/foxglove_bench.py", foxglove_table,
                      "Foxglove viewer"),
    "fuzz": Table("fuzz_load", "seeds", "python benchmarks/fuzz_load.py --seed 1 --seed 2 --seed 3", fuzz_table,
                  "Fuzz load"),
    "soak": Table("soak", "verdicts", "python benchmarks/soak.py", soak_table, "Soak"),
    "pixel_formats": Table("pixel_formats", "pairs", "python benchmarks/pixel_formats.py", pixel_formats_table,
                           "Pixel formats"),
    "upload": Table("upload", "throughput or S1", "python benchmarks/upload_bench.py", upload_table, "Upload"),
    "cli_latency": Table("cli_latency", "commands", "python benchmarks/cli_latency.py --runs 10", cli_latency_table,
                         "ipc-component latency"),
}


# ----------------------------------------------------------------------------------------------- result files
@dataclass
class Result:
    path: Path            # benchmarks/results/<folder>/<source>.json
    data: dict[str, Any]

    @property
    def started_at(self) -> str:
        return self.data.get("started_at", "")


def results(results_dir: Path) -> dict[str, list[Result]]:
    """Every result file under ``results_dir`` by source (``record``, ``replay``), the newest first."""
    found: dict[str, list[Result]] = {}
    for path in sorted(results_dir.glob("*/*.json")):
        found.setdefault(path.stem, []).append(Result(path, json.loads(path.read_text())))
    for entries in found.values():
        entries.sort(key=lambda result: (result.started_at, result.path.parent.name), reverse=True)
    return found


def caption(result: Result, doc: Path) -> str:
    """Where a generated block comes from: the command and the result file (a link relative to ``doc``)."""
    data = result.data
    link = Path(os.path.relpath(result.path, doc.parent)).as_posix()
    shown = result.path.relative_to(REPO if result.path.is_relative_to(REPO) else result.path.parents[2]).as_posix()
    git = data.get("git", {})
    return (f"Measured by `{data.get('command', '?')}` on the code of {git.get('commit', '?')}"
            f"{' with uncommitted changes' if git.get('modified') else ''}; results: [{shown}]({link}).")


def generated(name: str, found: dict[str, list[Result]], doc: Path) -> tuple[Optional[list[str]], str]:
    """The lines of block ``name`` for ``doc``, from the newest result file that gives it; or (None, why not)."""
    table = TABLES.get(name)
    if table is None:
        return None, f"no table is called {name!r} (known: {', '.join(TABLES)})"
    reasons = []
    for result in found.get(table.source, []):
        try:
            lines = table.make(result.data)
        except Missing as missing:
            reasons.append(f"{result.path.parent.name}: {missing}")
            continue
        return [*lines, "", caption(result, doc)], ""
    tried = f" (newest first: {'; '.join(reasons[:3])})" if reasons else ""
    return None, (f"needs {table.needs} in a {table.source}.json; no result folder has one{tried}. Run "
                  f"`{table.command}`, then this generator")


# ----------------------------------------------------------------------------------------------- files
def folder_tables(folder: Path) -> str:
    """The README.md of a result folder: every table its own JSON files give."""
    lines = [f"# Benchmark results {folder.name}", "",
             "Generated from the JSON files of this folder by `python -m benchmarks.report`; do not edit."]
    for path in sorted(folder.glob("*.json")):
        data = json.loads(path.read_text())
        git = data.get("git", {})
        lines += ["", f"## {path.name}", "", f"`{data.get('command', '?')}`, started {data.get('started_at', '?')}, "
                  f"code at {git.get('commit', '?')}"
                  + (f" + uncommitted changes in {', '.join(git['modified'])}" if git.get("modified") else "")
                  + f"; {data.get('elapsed_s', 0):.0f} s."]
        for table in TABLES.values():
            if table.source == path.stem and table.title:
                try:
                    lines += ["", f"### {table.title}", "", *table.make(data)]
                except Missing:
                    continue
    return "\n".join(lines) + "\n"


def write_folder_tables(folder: Path) -> None:
    (folder / FOLDER_TABLES).write_text(folder_tables(folder))


def shown(path: Path) -> str:
    """``path`` relative to the current directory when below it."""
    return str(path.relative_to(Path.cwd())) if path.is_relative_to(Path.cwd()) else str(path)


def regenerate(text: str, doc: Path, found: dict[str, list[Result]], notes: list[str]) -> str:
    """``text`` with every generated block rewritten; a note per block left as it is."""
    def replace(match: re.Match) -> str:
        lines, why = generated(match["name"], found, doc)
        if lines is None:
            notes.append(f"{shown(doc)}: block {match['name']!r} left as it is: {why}")
            return match[0]
        return (f"<!-- BEGIN GENERATED: {match['name']} -->\n" + "\n".join(lines)
                + f"\n<!-- END GENERATED: {match['name']} -->")

    return BLOCK.sub(replace, text)


def default_docs(repo: Path) -> list[Path]:
    return [path for path in [repo / "README.md", *sorted((repo / "docs").glob("*.md"))] if path.exists()]


def targets_of(results_dir: Path, docs: list[Path]) -> list[tuple[Path, str, list[str]]]:
    """(file, what it should hold, notes) for every doc and every result folder's table file."""
    found = results(results_dir)
    out = []
    for doc in docs:
        notes: list[str] = []
        out.append((doc, regenerate(doc.read_text(), doc, found, notes), notes))
    for folder in sorted({result.path.parent for entries in found.values() for result in entries}):
        out.append((folder / FOLDER_TABLES, folder_tables(folder), []))
    return out


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 if a file is out of date")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the directory of the result folders")
    parser.add_argument("--docs", type=Path, nargs="+", help="the files to rewrite (default: README.md, docs/*.md)")
    args = parser.parse_args(argv)
    stale = []
    for path, wanted, notes in targets_of(args.results, args.docs or default_docs(REPO)):
        for note in notes:
            print(note, file=sys.stderr)
        current = path.read_text() if path.exists() else ""
        if current == wanted:
            continue
        stale.append(path)
        if args.check:
            sys.stdout.writelines(difflib.unified_diff(current.splitlines(True), wanted.splitlines(True),
                                                       f"{shown(path)} (as it is)",
                                                       f"{shown(path)} (from the results)"))
        else:
            path.write_text(wanted)
            print(f"rewrote {shown(path)}")
    if args.check and stale:
        print(f"{len(stale)} file(s) differ from what the results give: run python -m benchmarks.report",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
