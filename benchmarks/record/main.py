"""Command line and sequence of a recording benchmark run: the direct-write limit, then S1, S2, S3 and S4 as
selected, the targets, the text report, the result folder."""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Optional

import rclpy

from benchmarks.record.bench import Bench, guarded
from benchmarks.record.compressed import CODECS, codec_of, run_s4
from benchmarks.record.disk import DIRECT_BLOCK, run_ceiling, run_direct_write
from benchmarks.record.figures import (apply_direct_share, apply_recorder_cpu, good, repeat_summary,
                                       s2_repeat_summary)
from benchmarks.record.measure import machine_identity
from benchmarks.record.modes import run_baseline, run_drivers_only, run_recorder_mode
from benchmarks.record.report import plot, print_report
from benchmarks.record.scenarios import RECORDER_MODES, s1_scenario, s2_scenario, s3_scenario
from benchmarks.record.targets import DEFAULT_CACHE, S2_CAMERAS, evaluate_targets
from benchmarks.result_folder import RESULTS, run_header, save

DESCRIPTION = "Recording benchmark: the zero-copy in-container recorder against DDS recording, on the same scenario."


def add_scenario_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=10.0, help="S1 measured window")
    p.add_argument("--cameras", type=int, default=2, help="S1 cameras")
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--lidar-points", type=int, default=131072)
    p.add_argument("--lidar-rate", type=float, default=10.0)
    p.add_argument("--imu-rate", type=float, default=200.0, help="S1 IMU rate")
    p.add_argument("--s2-seconds", type=float, default=6.0, help="S2 window per step")
    p.add_argument("--s2-max-cameras", type=int, default=8)
    p.add_argument("--s2-cameras", type=int, default=S2_CAMERAS,
                   help="with --repeat: S2's ipc step repeated at this many cameras")
    p.add_argument("--s2-base", choices=("rig", "cameras"), default="rig",
                   help="rig: cameras on top of the S1 lidar and IMU; cameras: cameras only")
    p.add_argument("--s3-seconds", type=float, default=10.0)
    p.add_argument("--s3-imus", type=int, default=10)
    p.add_argument("--s3-rate", type=float, default=1000.0)
    p.add_argument("--s4-seconds", type=float, default=5.0, help="S4 window per run")
    p.add_argument("--s4-codecs", default=",".join(CODECS), help="S4 codecs (comma-separated subset of "
                   + ",".join(CODECS) + "), each at the encoder's defaults, or codec:preset (h264:ultrafast)")
    p.add_argument("--s4-max-cameras", type=int, default=16,
                   help="S4: the most cameras a compressed codec's ramp runs (it starts near its codec limit)")
    p.add_argument("--s4-raw-cameras", type=int, default=8,
                   help="S4: raw's ramp (no codec limit to start from) starts at this many cameras, and runs no more")
    p.add_argument("--s4-cost-frames", type=int, default=120,
                   help="S4: frames encoded by each codec alone for its CPU time per frame (the codec limit)")
    p.add_argument("--s4-beside-cameras", type=int, default=1,
                   help="S4: cameras recorded raw and compressed at once, per codec")
    p.add_argument("--s4-psnr-frames", type=int, default=30,
                   help="S4: frames of camera 0 compared with their raw frames, spread over the window")
    p.add_argument("--baseline", metavar="REV",
                   help="S3 also records ipc with the code of this git revision (a temporary worktree) and the "
                        "single executor, for the target 'drivers + recorder CPU per message at most half of it'")


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    p.add_argument("--cache-mb", type=float, default=DEFAULT_CACHE / 2**20, help="storage.max_cache_size in MiB")
    p.add_argument("--executor", choices=("single", "multi", "isolated", "events"), default="single")
    p.add_argument("--threads", type=int, default=2, help="thread_num for --executor multi")
    p.add_argument("--settle", type=float, default=1.0, help="seconds between start_recording and the window")
    p.add_argument("--drain", type=float, default=1.0, help="seconds recorded after the window")
    p.add_argument("--startup-timeout", type=float, default=90.0)
    p.add_argument("--quiet-wait", type=float, default=15.0,
                   help="before each mode, wait up to this long for other processes to go quiet (0: never)")
    p.add_argument("--quiet-cpu", type=float, default=0.3, help="'quiet': other processes use at most this many CPUs")
    p.add_argument("--retries", type=int, default=1,
                   help="repeat a run during which other processes used more than --retry-cpu CPUs on average "
                        "this many times; the least perturbed run is reported")
    p.add_argument("--retry-cpu", type=float, default=0.5)
    p.add_argument("--ceiling-repeats", type=int, default=3,
                   help="ceiling runs per scenario, and direct-write runs; the median counts")
    p.add_argument("--direct-mb", type=float, default=2048.0,
                   help="MiB written with O_DIRECT to measure the direct-write limit of the bags' filesystem "
                        "(0: skip; at least 8)")
    p.add_argument("--repeat", type=int, default=0,
                   help="run S1's recorder modes this many times back to back and report the loss distribution, "
                        "and after S2's ramp its ipc step at --s2-cameras this many times (0: once, the plain "
                        "single-run output)")
    p.add_argument("--page-pause", type=float, default=10.0,
                   help="seconds between deleting a bag (or ceiling file) and the next run, so every run writes "
                        "to fresh page-cache pages as a continuously writing recorder does")


def add_output_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--output-dir", default=".", help="where the temporary bag directory is created")
    p.add_argument("--keep-bags", action="store_true", help="do not delete the bags (debugging)")
    p.add_argument("--results", default=str(RESULTS),
                   help="the result folder (record.json and its tables) goes under this directory ('': none)")
    p.add_argument("--json", metavar="FILE", help="also write the results as JSON to FILE ('-' for stdout)")
    p.add_argument("--plot", metavar="FILE", default=None,
                   help="PNG plot (needs matplotlib: the 'plot' extra); default: record.png in the result "
                        "folder; '' to skip")


def apply_quick(args: argparse.Namespace) -> None:
    """--quick: S1 only, short windows and pauses; still every S1 mode, so S1's ratio targets are evaluated."""
    args.scenarios = "s1"
    args.seconds = min(args.seconds, 3.0)
    args.page_pause = min(args.page_pause, 3.0)
    args.quiet_wait = min(args.quiet_wait, 5.0)
    args.ceiling_repeats = 1
    args.retries = 0


def parse_arguments(argv: Optional[list[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=DESCRIPTION + " See benchmarks/README.md.",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help="smoke run: S1 only, 3 s window, 3 s page pause, one ceiling and direct-write run, no retries")
    p.add_argument("--scenarios", default="s1,s2,s3,s4", help="comma-separated subset of s1,s2,s3,s4")
    p.add_argument("--modes", default="ipc,split,dds,drivers,ceiling",
                   help="S1/S3 modes to run (S2 always ipc,dds); split = ipc with --split-mb files (S1 only)")
    p.add_argument("--split-mb", type=float, default=256.0, help="storage.max_bagfile_size of the split mode, MiB")
    add_scenario_arguments(p)
    add_run_arguments(p)
    add_output_arguments(p)
    args = p.parse_args(argv)
    if args.quick:
        apply_quick(args)
    args.scenario_set = {s.strip().lower() for s in args.scenarios.split(",") if s.strip()}
    args.mode_set = {m.strip().lower() for m in args.modes.split(",") if m.strip()}
    unknown = (args.scenario_set - {"s1", "s2", "s3", "s4"}) | (args.mode_set - {*RECORDER_MODES, "drivers", "ceiling"})
    if unknown:
        p.error(f"unknown scenario/mode: {', '.join(sorted(unknown))}")
    if args.repeat < 0 or min(args.s2_cameras, args.s4_max_cameras, args.s4_raw_cameras, args.s4_beside_cameras,
                              args.s4_cost_frames) < 1:
        p.error("--repeat must be >= 0, --s2-cameras and every --s4-... count >= 1")
    if {codec_of(c.strip())[0] for c in args.s4_codecs.split(",") if c.strip()} - set(CODECS):
        p.error(f"--s4-codecs: each of {', '.join(CODECS)}, optionally with ':preset'")
    if 0 < args.direct_mb < DIRECT_BLOCK / 2**20:
        p.error(f"--direct-mb must be 0 (skip) or at least {DIRECT_BLOCK // 2**20}")
    return args


def run_s1_recorders(bench: Bench, run: int) -> dict[str, Any]:
    """One run of S1's selected recorder modes; ``run`` numbers it in the log under --repeat."""
    scenario = s1_scenario(bench.args)
    label = f" (run {run} of {bench.args.repeat})" if bench.args.repeat else ""
    return {mode: guarded(bench, f"S1 {mode}{label}", lambda: run_recorder_mode(bench, scenario, mode))
            for mode in RECORDER_MODES if mode in bench.args.mode_set}


def run_s1(bench: Bench) -> dict[str, Any]:
    """S1: the recorder modes (--repeat times), then drivers only and the ceiling once."""
    args = bench.args
    scenario = s1_scenario(args)
    runs = [run_s1_recorders(bench, run) for run in range(1, max(1, args.repeat) + 1)]
    s1: dict[str, Any] = {"scenario": scenario.summary(), **runs[0]}
    if "drivers" in args.mode_set:
        s1["drivers"] = guarded(bench, "S1 drivers only", lambda: run_drivers_only(bench, scenario))
    if "ceiling" in args.mode_set:
        s1["ceiling"] = guarded(bench, "S1 ceiling", lambda: run_ceiling(bench, scenario), retry=False)
    for run in runs:  # run 1's entries are s1's own
        apply_recorder_cpu({**run, "drivers": s1.get("drivers")})
    if args.repeat:
        s1["repeat"] = {"results": runs, **repeat_summary(runs)}
    return s1


def ramp(bench: Bench, s2: dict[str, Any], mode: str) -> None:
    """One camera more per step until ``mode`` loses messages (or the cap); at ipc's first lossy step, the
    ceiling of that step's bytes."""
    args = bench.args
    s2["largest_lossless"][mode], s2["limit_reached"][mode] = 0, False
    for cameras in range(1, args.s2_max_cameras + 1):
        scenario = s2_scenario(args, cameras)
        step = guarded(bench, f"S2 {mode} {cameras} camera(s)", lambda: run_recorder_mode(bench, scenario, mode))
        step.update({"mode": mode, "cameras": cameras})
        s2["steps"].append(step)
        if good(step) and step["lossless"]:
            s2["largest_lossless"][mode] = cameras
            continue
        s2["limit_reached"][mode] = True
        if mode == "ipc" and good(step):
            s2["ipc_overload"] = {"cameras": cameras, "mb_per_s": step["mb_per_s"]}
            ceiling = guarded(bench, f"S2 ceiling {cameras} camera(s)", lambda: run_ceiling(bench, scenario),
                              retry=False)
            if good(ceiling):
                s2["ceiling"] = {**ceiling, "cameras": cameras}
        return


def run_s2(bench: Bench) -> dict[str, Any]:
    """S2: the ramp, ipc then dds; with --repeat, ipc at --s2-cameras that many times back to back."""
    args = bench.args
    s2: dict[str, Any] = {"base": "S1 lidar + IMU + cameras" if args.s2_base == "rig" else "cameras only",
                          "cap": args.s2_max_cameras, "seconds": args.s2_seconds, "steps": [],
                          "largest_lossless": {}, "limit_reached": {}}
    for mode in ("ipc", "dds"):
        ramp(bench, s2, mode)
    if args.repeat:
        scenario = s2_scenario(args, args.s2_cameras)
        runs = [guarded(bench, f"S2 ipc {args.s2_cameras} cameras (run {run} of {args.repeat})",
                        lambda: run_recorder_mode(bench, scenario, "ipc")) for run in range(1, args.repeat + 1)]
        s2["repeat"] = {"cameras": args.s2_cameras, "results": runs, **s2_repeat_summary(runs)}
    return s2


def run_s3(bench: Bench) -> dict[str, Any]:
    """S3: ipc and dds as selected, the drivers alone, and --baseline."""
    args = bench.args
    scenario = s3_scenario(args)
    s3: dict[str, Any] = {"scenario": scenario.summary()}
    for mode in ("ipc", "dds"):
        if mode in args.mode_set:
            s3[mode] = guarded(bench, f"S3 {mode}", lambda: run_recorder_mode(bench, scenario, mode))
    if "drivers" in args.mode_set or "ipc" in args.mode_set:
        s3["drivers"] = guarded(bench, "S3 drivers only", lambda: run_drivers_only(bench, scenario))
    if args.baseline:
        s3["baseline"] = guarded(bench, f"S3 ipc, code at {args.baseline}, executor single",
                                 lambda: run_baseline(bench, scenario))
    apply_recorder_cpu(s3)
    return s3


def measure(bench: Bench, report: dict[str, Any]) -> None:
    """Every selected part of the run, in order, into ``report``."""
    if bench.args.direct_mb > 0:
        report["direct_write"] = guarded(bench, "direct-write limit", lambda: run_direct_write(bench), retry=False)
    for key, run in (("s1", run_s1), ("s2", run_s2), ("s3", run_s3), ("s4", run_s4)):
        if key in bench.args.scenario_set:
            report[key.upper()] = run(bench)


def write_outputs(report: dict[str, Any], args: argparse.Namespace, log: Any) -> None:
    """The text report (stdout; stderr with --json -), the result folder, the plot and --json."""
    with contextlib.redirect_stdout(sys.stderr if args.json == "-" else sys.stdout):
        print_report(report, args, {"S1": s1_scenario(args), "S3": s3_scenario(args)})
    folder = save(report, "record", Path(args.results)) if args.results else None
    if folder is not None:
        log(f"results: {folder.relative_to(Path.cwd()) if folder.is_relative_to(Path.cwd()) else folder}")
    plot_path = args.plot if args.plot is not None else (str(folder / "record.png") if folder else "")
    if plot_path:
        written = plot(report, Path(plot_path))
        log(f"plot written to {written}" if written else "no plot: matplotlib is not installed (pip install '.[plot]')")
    if args.json:
        text = json.dumps(report, indent=2, default=str)
        if args.json == "-":
            print(text)
        else:
            Path(args.json).write_text(text + "\n")


def main(argv: Optional[list[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_arguments(argv)
    output_dir = Path(args.output_dir).resolve()
    output_dir.mkdir(parents=True, exist_ok=True)
    workdir = Path(tempfile.mkdtemp(prefix="record_bench_", dir=output_dir))
    log = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    log(f"record_bench: ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}, bags in {workdir}, {os.cpu_count()} CPUs")
    report: dict[str, Any] = {**run_header("record_bench.py", argv),
                              "config": {k: v for k, v in vars(args).items() if not k.endswith("_set")},
                              "environment": {"ros_domain_id": os.environ["ROS_DOMAIN_ID"], "cpus": os.cpu_count(),
                                              "python": sys.version.split()[0], **machine_identity(),
                                              "workdir": str(workdir),
                                              "loadavg_start": os.getloadavg()}}
    started = time.monotonic()
    rclpy.init(args=["record_bench"])
    node = rclpy.create_node(f"record_bench_{os.getpid()}")
    try:
        measure(Bench(args, workdir, node, log=log), report)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        if not args.keep_bags:
            shutil.rmtree(workdir, ignore_errors=True)
    report["elapsed_s"] = time.monotonic() - started
    report["environment"]["loadavg_end"] = os.getloadavg()
    apply_direct_share(report)
    report["targets"] = evaluate_targets(report, args)
    write_outputs(report, args, log)
    return 0
