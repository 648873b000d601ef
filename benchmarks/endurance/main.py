"""Command line, verdicts, text report and result folder of the soak benchmark."""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import shutil
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Optional

import rclpy

from benchmarks.endurance.accounting import account
from benchmarks.endurance.bag_files import lower_priority
from benchmarks.endurance.churn import Churn, ChurnResult
from benchmarks.endurance.plan import SoakPlan, full_plan, short_plan
from benchmarks.endurance.resources import bound, evaluate
from benchmarks.result_folder import RESULTS, run_header, save


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(description="Soak: the S1 rig recorded for a long time while drivers, recorders "
                                            "and a player come and go; see benchmarks/README.md.",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--minutes", type=float, default=30.0, help="length of the churn (the S1 rig at full size)")
    p.add_argument("--short", action="store_true",
                   help="the test suite's run: 14 s, small frames, every period shortened")
    p.add_argument("--output-dir", default=".", help="where the temporary directory of the bags is created")
    p.add_argument("--keep-bags", action="store_true", help="do not delete the bags (debugging)")
    p.add_argument("--results", default=str(RESULTS),
                   help="the result folder (soak.json and its tables) goes under this directory ('': none)")
    p.add_argument("--json", metavar="FILE", help="also write the report as JSON to FILE")
    return p.parse_args(argv)


def verdicts(result: ChurnResult, accounting: dict[str, Any], resources: dict[str, Any],
             bags: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every pass / fail line of the run."""
    dropped = sum(bag["dropped"] for bag in bags)
    events = sum(len(bag["lost_events"]) for bag in bags)
    bag_problems = [f"{bag['name']}: {problem}" for bag in bags for problem in bag["problems"]]
    files = sum(bag["files"] for bag in bags)
    return [
        bound("the run went to its end", result.error is None, result.error or f"{result.churn_s:.0f} s of churn"),
        bound("zero loss: every sequence number accounted for", accounting["lost"] == 0
              and accounting["duplicates_in_one_bag"] == 0 and not result.extra_load_failures,
              f"{accounting['lost']} missing, {accounting['duplicates_in_one_bag']} twice in one bag, "
              f"{len(result.extra_load_failures)} extra loads failed"),
        bound("no drops reported (recorder counters, events/messages_lost)", dropped == 0 and events == 0,
              f"{dropped} dropped, {events} messages_lost events"),
        bound("every bag finalized, every file read by baglib and rosbags",
              not bag_problems and not result.problems and files > 0,
              f"{len(bags)} bags, {files} files; " + ("; ".join((bag_problems + result.problems)[:3]) or "no problem")),
        *resources["bounds"],
        bound("clean stop (container exit status 0)", result.exit_status == 0, f"exit status {result.exit_status}"),
    ]


def build_report(header: dict[str, Any], plan: SoakPlan, result: ChurnResult) -> dict[str, Any]:
    union = result.union
    numbered = [topic for topic, spec in plan.rig.topics().items() if spec.kind != "camera_info"]
    accounting = account(union, numbered, result.extra_instances, plan.replay_messages,
                         round(1e9 * plan.replay_messages / plan.replay_rate), result.replay_published)
    resources = evaluate(result.samples, plan.warmup_s)
    bags = [recorder.check or {"name": recorder.name, "files": 0, "dropped": 0, "lost_events": [],
                               "problems": ["never checked"]} for recorder in result.recorders]
    records = [record for recorder in result.recorders for record in recorder.files.values()]
    worker_cpu = sum(r.cpu_s for r in records)
    other = max(0.0, result.other_cpu_s - worker_cpu)  # other processes than the container and the worker
    report = {**header, "plan": plan.summary(),
              "churn": {"seconds": result.churn_s, "extra_instances": result.extra_instances,
                        "extra_load_failures": result.extra_load_failures, "recorders": len(result.recorders),
                        "handover_s": summary_of(result.handovers)},
              "files": {"count": len(records), "bytes": sum(r.size for r in records),
                        "messages": sum(r.messages for r in records),
                        "rosbags_read_messages": sum(r.rosbags_read for r in records),
                        "read_through_indexes": sum(1 for r in records if r.heads_only),
                        "read_seconds": summary_of([r.seconds for r in records]),
                        "worker_cpu_s": worker_cpu, "most_waiting": result.max_pending_files,
                        "reader_pauses": result.reader_pauses, "reader_paused_s": result.reader_paused_s},
              "bags": bags, "accounting": accounting, "resources": resources,
              "container": {"cpu_s": result.container_cpu_s, "cpus": result.container_cpu_s / max(result.churn_s, 1e-9),
                            "peak_rss_mib": result.peak_rss_mib, "exit_status": result.exit_status},
              "machine": {"other_cpu_s": other, "kernel_cpu_s": result.kernel_cpu_s,
                          "other_cpus": other / max(result.churn_s, 1e-9)},
              "problems": result.problems}
    report["verdicts"] = verdicts(result, accounting, resources, bags)
    return report


def summary_of(values: list[float]) -> Optional[dict[str, float]]:
    return {"min": min(values), "median": statistics.median(values), "max": max(values)} if values else None


def print_report(report: dict[str, Any]) -> None:
    files, churn, machine = report["files"], report["churn"], report["machine"]
    print(f"\n== Soak: {report['plan']['rig']['describe'].split(';')[0]}; {churn['seconds'] / 60:.1f} min of churn")
    print(f"  {churn['extra_instances']} extra drivers loaded and unloaded, {churn['recorders']} recorders, "
          f"{files['count']} files ({files['bytes'] / 1e9:.1f} GB, {files['messages']} messages; "
          f"{files['read_through_indexes']} files read through their message indexes, rosbags read "
          f"{files['rosbags_read_messages']} messages one by one; the reader stood aside {files['reader_pauses']} "
          f"times, {files['reader_paused_s']:.0f} s in all, while the recorder was behind)")
    for metric in ("rss_mib", "fds", "threads"):
        m = report["resources"].get(metric)
        if m:
            print(f"  {metric}: {m['start']:.1f} -> {m['end']:.1f}, slope {m['slope_per_hour']:+.1f}/h, "
                  f"thirds {m['first_third_max']:.1f} / {m['last_third_max']:.1f}")
    print(f"  container {report['container']['cpus']:.2f} CPUs on average; reading the files "
          f"{files['worker_cpu_s']:.0f} CPU s; other processes "
          f"{machine['other_cpus']:.2f} CPUs; load average {report['environment']['loadavg_start'][0]:.2f} -> "
          f"{report['environment']['loadavg_end'][0]:.2f}")
    for line in report["verdicts"]:
        print(f"  {line['result']:4}  {line['bound']}: {line['detail']}")
    for problem in report["problems"][:10]:
        print(f"  problem: {problem}")


def run(plan: SoakPlan, workdir: Path, keep_bags: bool) -> ChurnResult:
    """The churn with its worker process (spawned: the benchmark's own process runs rclpy threads)."""
    log = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    context = multiprocessing.get_context("spawn")
    rclpy.init(args=["soak"])
    node = rclpy.create_node(f"soak_{os.getpid()}")
    try:
        with ProcessPoolExecutor(max_workers=1, mp_context=context, initializer=lower_priority) as pool:
            return Churn(plan, workdir, node, pool, log, keep_bags).run()
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def main(argv: Optional[list[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_arguments(argv)
    plan = short_plan() if args.short else full_plan(args.minutes)
    output_dir = Path(args.output_dir).resolve()
    output_dir.mkdir(parents=True, exist_ok=True)
    workdir = Path(tempfile.mkdtemp(prefix="soak_", dir=output_dir))
    header = {**run_header("soak.py", argv),
              "environment": {"ros_domain_id": os.environ.get("ROS_DOMAIN_ID"), "cpus": os.cpu_count(),
                              "loadavg_start": os.getloadavg()}}
    started = time.monotonic()
    print(f"soak: ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID')}, work directory {workdir}", file=sys.stderr)
    try:
        result = run(plan, workdir, args.keep_bags)
    finally:
        if not args.keep_bags:
            shutil.rmtree(workdir, ignore_errors=True)
    header["environment"]["loadavg_end"] = os.getloadavg()
    report = build_report(header, plan, result)
    report["elapsed_s"] = time.monotonic() - started
    print_report(report)
    if args.results:
        print(f"results: {save(report, 'soak', Path(args.results))}", file=sys.stderr)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2, default=str) + "\n")
    return 0 if all(line["result"] != "FAIL" for line in report["verdicts"]) else 1
