"""The measured modes of a scenario: ``ipc``, ``split`` and ``dds`` (the recorder), ``drivers`` (the drivers
alone) and ``baseline`` (ipc with the code of another git revision).

Protocol of a recorder mode:

1. start the container process(es) from generated ``--load`` start-up files; the recorder records an explicit
   topic list (``record.topics``) into ``<work dir>/<run>`` (MCAP by default, default 100 MiB cache);
2. warm-up: poll ``~/get_stats`` until every expected topic has received messages, then ``~/stop_recording``
   (the warm-up bag is discarded) and ``~/start_recording`` (a fresh bag ``<run>_1`` with fresh latency
   samples), and wait ``--settle`` seconds;
3. the measured window ``[T0, T1]``: CPU of every process of the mode and of the machine at T0 and T1,
   ``~/get_stats`` at T1 (write_latency_ms p50/p99 over the session's latest writes);
4. ``--drain`` more seconds of recording (the window's last messages get recorded successors), then
   ``~/stop_recording`` (flushes and finalizes); peak RSS of every process; every process stopped by its pid;
5. the bag is read back with rosbags and deleted.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

from composition_interfaces.srv import ListNodes
from std_srvs.srv import Trigger

from benchmarks.record.bag_count import read_bag, window_counts
from benchmarks.record.bench import Bench
from benchmarks.record.measure import (GB, MB, Sample, dirty_pages_mb, peak_rss_mb, sleep_watching_dirty,
                                       source_skips, thread_cpu, thread_groups, window_cpu)
from benchmarks.record.scenarios import IPC_MODES, PUBLISH_RATE_OK, Scenario, TopicSpec
from ipc_testing import ContainerProcess, call, wait_until

REPO = Path(__file__).resolve().parents[2]
STOP_TIMEOUT = 30.0  # s a container gets to exit after SIGINT before it is killed


def start_container(bench: Bench, name: str, files: list[Path], executor: Optional[str] = None,
                    code: Optional[Path] = None) -> ContainerProcess:
    """``python -m component_container --executor E --load FILE...`` named ``name``, its output in a log file."""
    executor = executor or bench.args.executor
    argv = ["--executor", executor, *(part for path in files for part in ("--load", str(path)))]
    if executor == "multi":
        argv += ["--ros-args", "-p", f"thread_num:={bench.args.threads}"]
    return ContainerProcess(*argv, name=name, cwd=bench.workdir, log_path=bench.workdir / f"{name}.log", code=code)


class Processes:
    """The container processes of one run by label (``ipc`` / ``split``, or ``drivers`` and ``recorder``)."""

    def __init__(self, recorder: str) -> None:
        self.recorder = recorder  # the label of the process the recorder runs in
        self.by_label: dict[str, ContainerProcess] = {}

    def pids(self) -> dict[str, int]:
        return {label: process.pid for label, process in self.by_label.items()}

    def alive(self) -> bool:
        return all(process.alive() for process in self.by_label.values())

    def output(self) -> str:
        return "".join(process.output for process in self.by_label.values())

    def stop(self) -> None:
        for process in reversed(list(self.by_label.values())):
            process.stop(timeout=STOP_TIMEOUT, check=False)


def wait_for_service(client: Any, deadline: float, alive: Callable[[], bool]) -> None:
    """Until ``client``'s service is discovered; an error as soon as a container of the run has exited."""
    wait_until(lambda: client.service_is_ready() or not alive(), max(0.0, deadline - time.monotonic()))
    if not alive():
        raise RuntimeError(f"a container exited before {client.srv_name} appeared")
    if not client.service_is_ready():
        raise TimeoutError(f"{client.srv_name} did not appear")


class RecorderServices:
    """The recorder's ``~/get_stats``, ``~/stop_recording`` and ``~/start_recording`` (std_srvs/Trigger)."""

    VERBS = ("get_stats", "stop_recording", "start_recording")

    def __init__(self, node: Any, recorder: str) -> None:
        self.node = node
        self.clients = {verb: node.create_client(Trigger, f"/{recorder}/{verb}") for verb in self.VERBS}

    def wait(self, deadline: float, alive: Callable[[], bool]) -> None:
        for client in self.clients.values():
            wait_for_service(client, deadline, alive)

    def stats(self) -> dict[str, Any]:
        """``~/get_stats``: idempotent, so sent again until answered (Fast DDS drops a reply to a client whose
        reply reader the server has not matched yet)."""
        return json.loads(call(self.node, self.clients["get_stats"], timeout=60.0, again=True).message)

    def trigger(self, verb: str, timeout: float = 60.0, check: bool = True) -> Any:
        """``~/stop_recording`` or ``~/start_recording``, sent once; RuntimeError unless it succeeds (``check``)."""
        reply = call(self.node, self.clients[verb], timeout=timeout)
        if check and not reply.success:
            raise RuntimeError(f"{verb} failed: {reply.message}")
        return reply

    def destroy(self) -> None:
        for client in self.clients.values():
            self.node.destroy_client(client)


def recorder_component(name: str, topics: list[str], uri: Path, args: argparse.Namespace,
                       intra_process: bool, split_bytes: int = 0,
                       parameters: Optional[dict[str, Any]] = None) -> dict[str, Any]:
    """The recorder's entry of a ``--load`` file; ``parameters``: more of its parameters (``upload``: {...})."""
    return {"package": "components", "plugin": "components::Recorder", "name": name,
            "parameters": {"record": {"topics": topics},
                           "storage": {"uri": str(uri), "storage_id": args.storage,
                                       "max_cache_size": int(args.cache_mb * 1024 * 1024),
                                       "max_bagfile_size": split_bytes},
                           **(parameters or {})},
            "extra_arguments": {"use_intra_process_comms": intra_process}}


def start_mode(bench: Bench, tag: str, scenario: Scenario, mode: str, recorder: dict[str, Any]) -> Processes:
    """ipc / split: drivers and recorder in one container; dds: one container each, the recorder over DDS."""
    drivers = bench.write_yaml(f"{tag}_drivers", scenario.components())
    recorder_file = bench.write_yaml(f"{tag}_recorder", [recorder])
    if mode in IPC_MODES:
        processes = Processes(mode)
        processes.by_label[mode] = start_container(bench, f"bench_{tag}", [drivers, recorder_file],
                                                   bench.executor, bench.code)
        return processes
    processes = Processes("recorder")
    processes.by_label["drivers"] = start_container(bench, f"bench_{tag}_drivers", [drivers])
    processes.by_label["recorder"] = start_container(bench, f"bench_{tag}_recorder", [recorder_file])
    return processes


@dataclass
class Window:
    """What one recorder run measured while its processes ran."""

    start: Sample
    end: Sample
    warmup_s: float
    writer_tids: set[int]  # the measured session's bag-writer thread
    peak_dirty_mb: float
    live: dict[str, Any]   # ~/get_stats at the end of the window
    final: dict[str, Any]  # the final ~/stop_recording's report
    rss: dict[str, float]


def warm_up(services: RecorderServices, topics: dict[str, TopicSpec], deadline: float,
            alive: Callable[[], bool]) -> None:
    """Poll ``~/get_stats`` until every expected topic has reached the recorder."""
    while True:
        current = (services.stats().get("current") or {}).get("topics", {})
        missing = [t for t in topics if current.get(t, {}).get("received", 0) == 0]
        if not missing:
            return
        if not alive():
            raise RuntimeError("a container exited during warm-up")
        if time.monotonic() > deadline:
            raise TimeoutError(f"topics never reached the recorder: {', '.join(missing)}")
        time.sleep(0.2)


def record_window(bench: Bench, processes: Processes, services: RecorderServices, topics: dict[str, TopicSpec],
                  seconds: float, started_recording: Optional[Callable[[], None]] = None) -> Window:
    """Steps 2 to 4 of the protocol (module docstring); ``started_recording`` is called right after the measured
    bag began."""
    started = time.monotonic()
    deadline = started + bench.args.startup_timeout
    services.wait(deadline, processes.alive)
    warm_up(services, topics, deadline, processes.alive)
    warmup_s = time.monotonic() - started
    recorder_pid = processes.pids()[processes.recorder]
    threads_before = set(thread_cpu(recorder_pid))
    services.trigger("stop_recording")
    services.trigger("start_recording")
    writer_tids = set(thread_cpu(recorder_pid)) - threads_before  # the new session's writer thread
    if started_recording is not None:
        started_recording()
    time.sleep(bench.args.settle)
    pids = processes.pids()
    start = Sample.take(pids)
    peak_dirty = sleep_watching_dirty(seconds)
    end = Sample.take(pids)
    live = services.stats()["current"]
    time.sleep(bench.args.drain)
    final_reply = services.trigger("stop_recording", timeout=120.0, check=False)
    final = json.loads(final_reply.message) if final_reply.message.startswith("{") else {}
    rss = {label: peak_rss_mb(pid) for label, pid in pids.items()}
    if not processes.alive():
        raise RuntimeError("a container died during the measurement")
    return Window(start, end, warmup_s, writer_tids, peak_dirty, live, final, rss)


def window_result(start: Sample, end: Sample, pids: dict[str, int], writer_label: str = "",
                  writer_tids: Optional[set[int]] = None) -> dict[str, Any]:
    """CPU over the window per process, per thread group and of the rest of the machine."""
    out = window_cpu(start, end, pids)
    out["thread_cpu_s"] = {label: thread_groups(start.threads[label], end.threads[label],
                                                (writer_tids or set()) if label == writer_label else set())
                           for label in pids}
    return out


def recording_result(read: dict[str, Any], window: Window, topics: dict[str, TopicSpec]) -> dict[str, Any]:
    """What the bag holds of the window: per topic and in total (published, recorded, lost, bytes)."""
    counts = window_counts(read["records"], topics, window.start.time_ns, window.end.time_ns)
    window_s = (window.end.time_ns - window.start.time_ns) / 1e9
    recorded_bytes = sum(c["bytes"] for c in counts.values())
    bag_total = sum(len(v) for v in read["records"].values())
    written = sum(t.get("written", 0) for t in window.final.get("topics", {}).values())
    totals = {key: sum(c[key] for c in counts.values()) for key in ("published", "recorded", "lost", "duplicates")}
    return {"topics": counts, **totals, "min_pub_ratio": min(c["pub_ratio"] for c in counts.values()),
            "recorded_bytes": recorded_bytes, "mb_per_s": recorded_bytes / MB / window_s,
            "lost_pct": 100.0 * totals["lost"] / totals["published"] if totals["published"] else 0.0,
            "latency_ms": window.live.get("write_latency_ms"), "recorder_counters": window.final.get("topics"),
            "recorder_error": window.final.get("error"), "bag_messages": bag_total,
            **backlog_result(window),
            "bag_metadata_messages": read["metadata_count"], "bag_matches_recorder_written": bag_total == written}


def backlog_result(window: Window) -> dict[str, Any]:
    """How far the recorder's writer was behind: its peak backlog over the whole recording (settle, window and
    drain), its backlog at the end of the window, and whether that was within ``max_cache_size`` again. A writer
    slower than the rig falls further behind for the whole window and ends it deep in the stall reserve: lossless
    then only for as long as the reserve lasts, not a rate it sustains; a writer that went into the reserve for a
    moment and caught up ends it within its cache."""
    stats = window.final if "peak_backlog_bytes" in window.final else window.live
    peak, end, cache = (stats.get("peak_backlog_bytes"), window.live.get("backlog_bytes"),
                        window.live.get("max_cache_size"))
    return {"peak_backlog_mb": None if peak is None else peak / MB,
            "end_backlog_mb": None if end is None else end / MB,
            "within_cache": None if end is None or cache is None else end <= cache}


def run_recorder_mode(bench: Bench, scenario: Scenario, mode: str,
                      recorder_parameters: Optional[dict[str, Any]] = None,
                      started_recording: Optional[Callable[[Processes, RecorderServices], None]] = None,
                      before_stop: Optional[Callable[[Processes, RecorderServices], dict[str, Any]]] = None
                      ) -> dict[str, Any]:
    """``ipc``, ``split`` or ``dds`` on one scenario; see the module docstring for the protocol.

    For a benchmark of something the recorder does beside recording (benchmarks/upload_bench.py):
    ``recorder_parameters`` are added to the recorder's; ``started_recording`` is called as the measured bag
    begins, ``before_stop`` once it is finalized, before the containers stop; what it returns goes into the
    result."""
    args = bench.args
    tag = bench.next_tag(scenario, mode)
    topics = scenario.topics()
    uri = bench.workdir / tag
    recorder = recorder_component(f"rec_{tag}", list(topics), uri, args, intra_process=mode in IPC_MODES,
                                  split_bytes=int(args.split_mb * 1024 * 1024) if mode == "split" else 0,
                                  parameters=recorder_parameters)
    processes = start_mode(bench, tag, scenario, mode, recorder)
    services = RecorderServices(bench.node, f"rec_{tag}")
    extra: dict[str, Any] = {}
    try:
        window = record_window(bench, processes, services, topics, scenario.seconds,
                               started_recording and (lambda: started_recording(processes, services)))
        if before_stop is not None:
            extra = before_stop(processes, services)
    finally:
        services.destroy()
        processes.stop()
    bag = Path(f"{uri}_1")
    result: dict[str, Any] = {"mode": mode, "scenario": scenario.key, "cameras": scenario.cameras,
                              "warmup_s": window.warmup_s, "source_skips_logged": source_skips(processes.output()),
                              "bag_files": len(list(bag.glob("*.mcap")) + list(bag.glob("*.db3")))}
    try:
        read = read_bag(bag, scenario, topics)
    finally:
        bench.discard_bags(bag, uri)
    result.update(window_result(window.start, window.end, processes.pids(), processes.recorder, window.writer_tids))
    result.update(recording_result(read, window, topics))
    result.update({"peak_dirty_mb": window.peak_dirty_mb, "dirty_threshold_mb": dirty_pages_mb()[1],
                   "peak_rss_mb": window.rss, "recorder_rss_mb": window.rss[processes.recorder],
                   "recorder_cpu_s": result["cpu_s"]["recorder"] if mode == "dds" else None,
                   "writer_thread_cpu_s": (result["thread_cpu_s"][processes.recorder].get("bag writer")
                                           if len(window.writer_tids) == 1 else None),
                   "total_cpu_s_per_gb": (result["total_cpu_s"] / (result["recorded_bytes"] / GB)
                                          if result["recorded_bytes"] else None),
                   "lossless": (result["lost"] == 0 and result["min_pub_ratio"] >= PUBLISH_RATE_OK
                                and not result["recorder_error"])})
    result.update(extra)
    return result


def run_drivers_only(bench: Bench, scenario: Scenario) -> dict[str, Any]:
    """The drivers alone: CPU and RSS over a window of the same length."""
    args = bench.args
    tag = bench.next_tag(scenario, "drivers")
    drivers = scenario.components()
    container = start_container(bench, f"bench_{tag}", [bench.write_yaml(f"{tag}_drivers", drivers)])
    client = bench.node.create_client(ListNodes, f"/bench_{tag}/_container/list_nodes")
    pids = {"drivers": container.pid}
    try:
        wait_for_service(client, time.monotonic() + args.startup_timeout, container.alive)
        names = call(bench.node, client, timeout=args.startup_timeout, again=True).full_node_names
        if len(names) != len(drivers):
            raise RuntimeError(f"only {len(names)} of {len(drivers)} drivers loaded")
        time.sleep(args.settle + 1.0)
        start = Sample.take(pids)
        time.sleep(scenario.seconds)
        end = Sample.take(pids)
        rss = peak_rss_mb(container.pid)
        if not container.alive():
            raise RuntimeError("the drivers container died during the measurement")
    finally:
        bench.node.destroy_client(client)
        container.stop(timeout=STOP_TIMEOUT, check=False)
    return {"mode": "drivers", "scenario": scenario.key, **window_result(start, end, pids),
            "peak_rss_mb": {"drivers": rss}, "source_skips_logged": source_skips(container.output)}


def run_baseline(bench: Bench, scenario: Scenario) -> dict[str, Any]:
    """S3 ipc once more, with the code of ``--baseline`` (checked out into a temporary worktree, imported first
    through PYTHONPATH) and the single executor: what the current code's CPU per message is compared with."""
    checkout = bench.workdir / "baseline_code"
    subprocess.run(["git", "worktree", "add", "--detach", "--force", str(checkout), bench.args.baseline],
                   cwd=REPO, check=True, capture_output=True, timeout=120)
    bench.code, bench.executor = checkout, "single"
    try:
        result = run_recorder_mode(bench, scenario, "ipc")
    finally:
        bench.code, bench.executor = None, None
        subprocess.run(["git", "worktree", "remove", "--force", str(checkout)], cwd=REPO, capture_output=True,
                       timeout=120)
    result["mode"] = "baseline"
    result["code"] = bench.args.baseline
    return result
