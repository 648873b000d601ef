#!/usr/bin/env python3
"""Uploading bags to S3-compatible storage: this project's uploader against boto3's own ``upload_file``, and what
uploading at full speed costs a recording of the S1 rig. One run, side by side, against a real nanio server on
loopback (ipc_testing/s3_server.py) on the same machine:

* **throughput**: one bag of real MCAP files (ipc_testing/camera_bag.py: 1080p rgb8 camera frames with random
  pixels and an IMU, split every ``--file-mb``), uploaded whole, ``--rounds`` times by each client in
  alternation (the order swapped every round), each in a process of its own (benchmarks/upload_client.py):
  ``boto3`` (s3transfer at its defaults) and ``ours`` (``upload_bags``, what ``ipc-component bag upload`` and the
  recorder's upload process run). Per run: MB/s, the client's CPU seconds per GB (measured inside the process,
  over the upload alone), the server's, and what the rest of the machine used meanwhile. Target: ours at 80 % or
  more of boto3's MB/s (medians over the rounds).
* **S1**: the S1 rig (2 x 1920x1080 rgb8 at 30 Hz, a LiDAR of 131072 points at 10 Hz, an IMU at 200 Hz) recorded
  in the drivers' container, split every ``--split-mb``, with ``upload.uri`` set (``upload.max_rate`` 0: each
  file uploaded as soon as it is closed, at full speed) and without; the drivers alone for the recorder's own
  CPU (benchmarks/record/modes.py, as record_bench.py measures S1). Per mode: frames published, recorded and
  lost (the bag read back), the container's and the recorder's CPU per GB written; with upload, the upload
  process's CPU per GB uploaded and the server's, from the measured bag's start until every file of it is in
  the store. Target: 0 frames lost with upload on.

    python benchmarks/upload_bench.py [--rounds 3] [--upload-mb 600] [--seconds 6] [--parts throughput,s1]

Results: benchmarks/results/<date>-<commit>/upload.json.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import isolation  # noqa: F401  (first: the ROS environment before rclpy is imported)

import rclpy  # noqa: E402
from rclpy.node import Node  # noqa: E402

from baglib.upload.bag_upload import bag_files  # noqa: E402
from benchmarks.fleet_bench import cpu_seconds  # noqa: E402
from benchmarks.record.bench import Bench, guarded  # noqa: E402
from benchmarks.record.figures import apply_recorder_cpu  # noqa: E402
from benchmarks.record.main import add_run_arguments as add_recorder_arguments  # noqa: E402
from benchmarks.record.measure import GB, MB, machine_busy_seconds  # noqa: E402
from benchmarks.record.modes import Processes, RecorderServices, run_drivers_only, run_recorder_mode  # noqa: E402
from benchmarks.record.scenarios import Scenario  # noqa: E402
from benchmarks.result_folder import (add_location_arguments, run_environment, run_header, save,  # noqa: E402
                                      work_directory)
from ipc_testing import wait_until  # noqa: E402
from ipc_testing.camera_bag import write_camera_bag  # noqa: E402
from ipc_testing.s3_server import S3Server  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CLIENT = REPO / "benchmarks" / "upload_client.py"
CLIENTS = ("boto3", "ours")
BUCKET = "bench"
PARTS = ("throughput", "s1")
#: Ours against boto3's upload_file, MB/s (the issue's target).
TARGET_RATIO = 0.8
FRAME_BYTES = 1920 * 1080 * 3
MiB = 1 << 20


# ----------------------------------------------------------------------------------------------- throughput
def delete_prefix(server: S3Server, prefix: str) -> int:
    """Delete every object under ``prefix``/ (the server's disk stays as small as one run); how many."""
    client = server.client()
    keys = [item["Key"] for page in client.get_paginator("list_objects_v2").paginate(Bucket=BUCKET,
                                                                                     Prefix=prefix + "/")
            for item in page.get("Contents", [])]
    for start in range(0, len(keys), 1000):
        client.delete_objects(Bucket=BUCKET, Delete={"Objects": [{"Key": key} for key in keys[start:start + 1000]]})
    return len(keys)


def children_cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def upload_run(client: str, bag: Path, server: S3Server, prefix: str, size: int) -> dict[str, Any]:
    """One upload of ``bag`` under ``prefix`` by ``client`` in a process of its own; its figures."""
    assert server.process is not None
    busy, server_cpu, children, started = (machine_busy_seconds(), cpu_seconds(server.process.pid),
                                           children_cpu_seconds(), time.monotonic())
    done = subprocess.run([sys.executable, str(CLIENT), client, str(bag), f"s3://{BUCKET}/{prefix}",
                           server.endpoint_url], env={**os.environ, **server.env()}, capture_output=True, text=True,
                          timeout=600, cwd=REPO)
    wall = time.monotonic() - started
    if done.returncode:
        raise RuntimeError(f"{client} failed: {done.stderr[-2000:]}")
    inside = json.loads(done.stdout.splitlines()[-1])
    process_cpu = children_cpu_seconds() - children
    server_cpu = cpu_seconds(server.process.pid) - server_cpu
    objects = delete_prefix(server, prefix)
    return {"client": client, "seconds": inside["seconds"], "mb_per_s": size / MB / inside["seconds"],
            "cpu_s": inside["cpu_s"], "cpu_s_per_gb": inside["cpu_s"] / (size / GB),
            "process_cpu_s_with_start": process_cpu, "server_cpu_s": server_cpu,
            "server_cpu_s_per_gb": server_cpu / (size / GB), "objects": objects,
            "other_cpus": max(0.0, machine_busy_seconds() - busy - process_cpu - server_cpu) / wall,
            "loadavg": os.getloadavg()[0]}


def measure_throughput(args: argparse.Namespace, workdir: Path, server: S3Server) -> dict[str, Any]:
    bag = workdir / "throughput" / "bag"  # a directory of its own: its own upload journal
    frames = max(1, round(args.upload_mb * MB / FRAME_BYTES / 2))
    counts = write_camera_bag(bag, frames, max_bagfile_size=int(args.file_mb * MiB))
    files = bag_files(bag)
    size = sum(path.stat().st_size for path in files)
    print(f"throughput: {len(files)} files, {size / MB:.0f} MB, {args.rounds} round(s)", flush=True)
    runs = []
    for number in range(args.rounds):
        for client in CLIENTS if number % 2 == 0 else CLIENTS[::-1]:
            run = upload_run(client, bag, server, f"round{number}-{client}", size)
            run["round"] = number
            runs.append(run)
            print(f"  round {number} {client}: {run['mb_per_s']:.0f} MB/s, client {run['cpu_s_per_gb']:.2f} CPU s/GB, "
                  f"server {run['server_cpu_s_per_gb']:.2f} CPU s/GB, others {run['other_cpus']:.2f} CPUs",
                  flush=True)
    per_client = {client: {key: statistics.median(run[key] for run in runs if run["client"] == client)
                           for key in ("mb_per_s", "cpu_s_per_gb", "server_cpu_s_per_gb", "other_cpus")}
                  for client in CLIENTS}
    ratio = per_client["ours"]["mb_per_s"] / per_client["boto3"]["mb_per_s"]
    round_ratios = [next(r["mb_per_s"] for r in runs if r["round"] == n and r["client"] == "ours")
                    / next(r["mb_per_s"] for r in runs if r["round"] == n and r["client"] == "boto3")
                    for n in range(args.rounds)]
    return {"bag": {"files": [path.name for path in files], "bytes": size, "messages": counts},
            "runs": runs, "median": per_client, "ratio": ratio, "round_ratios": round_ratios,
            "target": {"target": f"ours >= {TARGET_RATIO:.0%} of boto3's upload_file (MB/s, medians)",
                       "result": "met" if ratio >= TARGET_RATIO else "missed", "detail": f"{ratio:.0%}"}}


# ----------------------------------------------------------------------------------------------- S1
def worker_pid(container: int) -> int:
    """The pid of the upload process (``python -m baglib.upload.worker``) the container started."""
    for task in Path(f"/proc/{container}/task").iterdir():
        for child in (task / "children").read_text().split():
            if "baglib.upload.worker" in Path(f"/proc/{child}/cmdline").read_text(errors="replace"):
                return int(child)
    raise RuntimeError(f"container {container} runs no upload process")


class UploadWatch:
    """The upload of an S1 run with upload on: from the measured bag's start (``started``) until every file of
    both of the run's bags (the warm-up's and the measured one) is in the store (``finished``): the upload
    process's CPU, the server's and the bytes sent meanwhile."""

    def __init__(self, server: S3Server, prefix: str, timeout: float) -> None:
        self.server, self.prefix, self.timeout = server, prefix, timeout
        self.start: dict[str, float] = {}
        self.pid = 0

    def sample(self, services: RecorderServices) -> dict[str, float]:
        assert self.server.process is not None
        return {"time": time.monotonic(), "worker": cpu_seconds(self.pid),
                "server": cpu_seconds(self.server.process.pid), "sent": services.stats()["upload"]["bytes_sent"]}

    def started(self, processes: Processes, services: RecorderServices) -> None:
        self.pid = worker_pid(processes.pids()[processes.recorder])
        self.start = self.sample(services)

    def bags_in_store(self) -> int:
        listing = self.server.client().get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=self.prefix)
        return sum(item["Key"].endswith("/metadata.yaml") for page in listing for item in page.get("Contents", []))

    def finished(self, processes: Processes, services: RecorderServices) -> dict[str, Any]:
        stopped = time.monotonic()
        if not wait_until(lambda: services.stats()["upload"]["complete"] and self.bags_in_store() >= 2,
                          self.timeout, interval=0.5):
            raise TimeoutError(f"the upload did not complete within {self.timeout:g} s: "
                               f"{services.stats()['upload']}")
        end = self.sample(services)
        state = services.stats()["upload"]
        sent = end["sent"] - self.start["sent"]
        return {"upload": {
            "bytes_sent": sent, "seconds": end["time"] - self.start["time"],
            "mb_per_s": sent / MB / (end["time"] - self.start["time"]),
            "complete_after_stop_s": end["time"] - stopped,
            "cpu_s": end["worker"] - self.start["worker"],
            "cpu_s_per_gb": (end["worker"] - self.start["worker"]) / (sent / GB),
            "server_cpu_s_per_gb": (end["server"] - self.start["server"]) / (sent / GB),
            "files_uploaded": state["files_uploaded"], "verify_mismatches": state["verify_mismatches"],
            "deleted_before_upload": state["deleted_before_upload"], "last_error": state["last_error"]}}


def measure_s1(args: argparse.Namespace, bench: Bench, server: S3Server) -> dict[str, Any]:
    scenario = Scenario("S1", "S1 multi-camera rig", args.seconds, cameras=2, lidar_points=131072, imus=1)
    watch = UploadWatch(server, "s1/", args.upload_timeout)
    upload = {"upload": {"uri": f"s3://{BUCKET}/s1", "endpoint_url": server.endpoint_url, "max_rate": 0.0}}
    modes: dict[str, Callable[[], dict[str, Any]]] = {
        "drivers": lambda: run_drivers_only(bench, scenario),
        "upload_off": lambda: run_recorder_mode(bench, scenario, "split"),
        "upload_on": lambda: run_recorder_mode(bench, scenario, "split", upload, watch.started, watch.finished)}
    results = {mode: guarded(bench, f"S1 {mode}", run) for mode, run in modes.items()}
    for mode in ("upload_off", "upload_on"):
        apply_recorder_cpu({"drivers": results["drivers"], "split": results[mode]})
    on = results["upload_on"]
    lossless = "error" not in on and on["lossless"] and on["lost"] == 0
    return {"scenario": scenario.summary(), "split_mb": args.split_mb, **results,
            "target": {"target": "S1 with upload on at full speed loses 0 frames",
                       "result": "met" if lossless else "missed",
                       "detail": on.get("error") or f"{on['lost']} of {on['published']} lost"}}


# ----------------------------------------------------------------------------------------------- main
def parse_arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", default=",".join(PARTS), help="comma-separated subset of " + ",".join(PARTS))
    parser.add_argument("--rounds", type=int, default=3, help="throughput: uploads by each client, alternated")
    parser.add_argument("--upload-mb", type=float, default=600.0, help="throughput: the bag's size in MB")
    parser.add_argument("--file-mb", type=float, default=128.0, help="throughput: the bag's files' size in MiB")
    parser.add_argument("--seconds", type=float, default=6.0, help="S1: the measured window")
    parser.add_argument("--split-mb", type=float, default=256.0, help="S1: storage.max_bagfile_size in MiB")
    parser.add_argument("--upload-timeout", type=float, default=300.0,
                        help="S1: seconds the upload may take to complete after the recording stopped")
    parser.add_argument("--keep-bags", action="store_true", help="do not delete the S1 bags (debugging)")
    parser.add_argument("--quick", action="store_true", help="one round of 300 MB, a 3 s S1 window")
    add_recorder_arguments(parser)
    parser.set_defaults(quiet_wait=5.0, retries=0, page_pause=5.0)
    add_location_arguments(parser)
    args = parser.parse_args()
    if args.quick:
        args.rounds, args.upload_mb, args.seconds = 1, min(args.upload_mb, 300.0), min(args.seconds, 3.0)
    unknown = set(args.parts.split(",")) - set(PARTS)
    if unknown:
        parser.error(f"unknown --parts {', '.join(sorted(unknown))}")
    return args


def main() -> int:
    args = parse_arguments()
    report: dict[str, Any] = {**run_header("upload_bench.py", sys.argv[1:]), "environment": run_environment()}
    started = time.monotonic()
    with work_directory(args, "upload_bench_") as workdir_name:
        workdir = Path(workdir_name)
        with S3Server(workdir / "s3", log=workdir / "s3.log") as server:
            os.environ.update(server.env())  # the containers' upload processes find the server's credentials
            server.client().create_bucket(Bucket=BUCKET)
            report["server"] = "nanio on 127.0.0.1 (same machine)"
            if "throughput" in args.parts:
                report["throughput"] = measure_throughput(args, workdir, server)
            if "s1" in args.parts:
                rclpy.init()
                node = Node("upload_bench")
                try:
                    report["S1"] = measure_s1(args, Bench(args, workdir, node), server)
                finally:
                    node.destroy_node()
                    rclpy.shutdown()
    report["elapsed_s"] = time.monotonic() - started
    report["environment"]["loadavg_end"] = os.getloadavg()
    print(json.dumps({part: report[part].get("target") for part in ("throughput", "S1") if part in report}))
    if args.results:
        print(f"results: {save(report, 'upload', Path(args.results))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
