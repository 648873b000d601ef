"""The write limits a recorder is compared with, measured on the filesystem the bags go to, in the same run.

* **ceiling**: a plain Python loop writing a scenario's nominal bytes, in the same message sizes and order, with
  buffered writes (what this machine's page cache lets a writer do); the median of ``--ceiling-repeats`` runs,
  each after the page pause, plus one "warm" run straight after a deletion (reusing just-freed pages);
* **direct-write limit**: ``--direct-mb`` MiB written with ``O_DIRECT`` (``baglib.write.direct_file``) in
  8 MiB page-aligned blocks of random bytes, then fsync: the disk's own sequential-write bandwidth (what
  ``dd oflag=direct`` reports), the physical limit a recorder can approach. The buffered ceiling may exceed it
  for a while, as long as the page cache absorbs the writes.
"""
from __future__ import annotations

import json
import mmap
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

from benchmarks.record.bench import Bench
from benchmarks.record.measure import GB, MB, machine_snapshot, other_cpu
from benchmarks.record.scenarios import Scenario

DIRECT_BLOCK = 8 * 1024 * 1024  # bytes per O_DIRECT write (a multiple of every block size)

CEILING_WORKER = textwrap.dedent("""
    import json, os, sys, time
    spec = json.load(open(sys.argv[1]))
    sizes = spec["sizes"]
    buffer = memoryview(os.urandom(max(sizes)))
    cpu0, t0 = time.process_time(), time.perf_counter()
    with open(spec["path"], "wb") as out:
        for size in sizes:
            out.write(buffer[:size])
    t1, cpu1 = time.perf_counter(), time.process_time()
    fd = os.open(spec["path"], os.O_RDONLY)
    os.fsync(fd)
    os.close(fd)
    t2 = time.perf_counter()
    print(json.dumps({"seconds": t1 - t0, "cpu_s": cpu1 - cpu0, "fsync_s": t2 - t1, "bytes": sum(sizes)}))
""")


def ceiling_once(spec_path: Path, data_path: Path) -> dict[str, Any]:
    """One run of the ceiling writer (a fresh process), the file deleted after it."""
    machine0 = machine_snapshot()
    done = subprocess.run([sys.executable, "-c", CEILING_WORKER, str(spec_path)], capture_output=True, text=True,
                          timeout=600)
    machine1 = machine_snapshot()
    data_path.unlink(missing_ok=True)
    if done.returncode != 0:
        raise RuntimeError(f"ceiling writer failed: {done.stderr.strip()}")
    out = json.loads(done.stdout)
    # other processes, and the kernel (its writeback of this file included), during the writer's life
    out["background_cpu_s"], out["kernel_cpu_s"] = other_cpu(machine0, machine1, out["cpu_s"], {os.getpid()})
    return out


def run_ceiling(bench: Bench, scenario: Scenario) -> dict[str, Any]:
    """Write the scenario's nominal bytes, message by message in due order, as fast as Python can.

    Each counted run waits for the page pause first (a continuously writing recorder gets fresh pages); one
    more run straight after a deletion is the warm, burst figure.
    """
    events: list[tuple[float, int]] = []
    for spec in scenario.topics().values():
        events += [(k / spec.rate, spec.size) for k in range(round(spec.rate * scenario.seconds))]
    events.sort()
    tag = bench.next_tag(scenario, "ceiling")
    spec_path, data_path = bench.workdir / f"{tag}.json", bench.workdir / f"{tag}.bin"
    spec_path.write_text(json.dumps({"path": str(data_path), "sizes": [size for _, size in events]}))
    runs = []
    try:
        for _ in range(max(1, bench.args.ceiling_repeats)):
            bench.wait_for_fresh_pages()
            runs.append(ceiling_once(spec_path, data_path))
            bench.last_free = time.monotonic()
        warm = ceiling_once(spec_path, data_path)
    finally:
        data_path.unlink(missing_ok=True)
        spec_path.unlink(missing_ok=True)
        bench.last_free = time.monotonic()
    out = sorted(runs, key=lambda r: r["seconds"])[len(runs) // 2]
    return {"mode": "ceiling", "scenario": scenario.key, "recorded_bytes": out["bytes"], "messages": len(events),
            "write_s": out["seconds"], "window_s": out["seconds"] + out["fsync_s"],
            "mb_per_s": out["bytes"] / MB / out["seconds"],
            "mb_per_s_with_fsync": out["bytes"] / MB / (out["seconds"] + out["fsync_s"]),
            "total_cpu_s": out["cpu_s"], "total_cpu_s_per_gb": out["cpu_s"] / (out["bytes"] / GB),
            "background_cpu_s": out["background_cpu_s"], "kernel_cpu_s": out["kernel_cpu_s"],
            "all_runs_mb_per_s": [r["bytes"] / MB / r["seconds"] for r in runs],
            "all_runs_cpu_s_per_gb": [r["cpu_s"] / (r["bytes"] / GB) for r in runs],
            "warm_mb_per_s": warm["bytes"] / MB / warm["seconds"],
            "warm_cpu_s_per_gb": warm["cpu_s"] / (warm["bytes"] / GB)}


def direct_write_once(path: Path, total: int) -> dict[str, Any]:
    """Write ``total`` bytes (whole 8 MiB blocks) to a new file with O_DIRECT, fsync; seconds and CPU."""
    from baglib.write.direct_file import DirectFile, open_exclusive
    out = open_exclusive(path, buffering=0)
    if not isinstance(out, DirectFile):  # open_exclusive falls back to a buffered file without O_DIRECT
        out.close()
        raise RuntimeError(f"the filesystem of {path.parent} does not support O_DIRECT")
    block = mmap.mmap(-1, DIRECT_BLOCK)  # anonymous mappings are page-aligned, as O_DIRECT needs
    block.write(os.urandom(DIRECT_BLOCK))
    view = memoryview(block)
    try:
        cpu0, t0 = time.process_time(), time.perf_counter()
        for _ in range(total // DIRECT_BLOCK):
            done = 0
            while done < DIRECT_BLOCK:
                done += os.write(out.fileno(), view[done:])
        t1 = time.perf_counter()
        out.close(sync=True)
        t2, cpu1 = time.perf_counter(), time.process_time()
    finally:
        out.close()
        view.release()
        block.close()
    return {"bytes": total // DIRECT_BLOCK * DIRECT_BLOCK, "write_s": t1 - t0, "fsync_s": t2 - t1,
            "cpu_s": cpu1 - cpu0}


def run_direct_write(bench: Bench) -> dict[str, Any]:
    """The direct-write limit of the bags' filesystem: the median of --ceiling-repeats runs."""
    path = bench.workdir / "direct_write.bin"
    total = int(bench.args.direct_mb * 2**20)
    runs = []
    try:
        for _ in range(max(1, bench.args.ceiling_repeats)):
            bench.wait_for_fresh_pages()
            machine0 = machine_snapshot()
            run = direct_write_once(path, total)
            machine1 = machine_snapshot()
            path.unlink()
            bench.last_free = time.monotonic()
            run["background_cpu_s"], run["kernel_cpu_s"] = other_cpu(machine0, machine1, run["cpu_s"], {os.getpid()})
            run["mb_per_s"] = run["bytes"] / MB / (run["write_s"] + run["fsync_s"])
            runs.append(run)
    finally:
        path.unlink(missing_ok=True)
    median = sorted(runs, key=lambda r: r["mb_per_s"])[len(runs) // 2]
    return {"mode": "direct", "path": str(path.parent), "block_bytes": DIRECT_BLOCK, **median,
            "window_s": median["write_s"] + median["fsync_s"],
            "cpu_s_per_gb": median["cpu_s"] / (median["bytes"] / GB),
            "all_runs_mb_per_s": [r["mb_per_s"] for r in runs]}
