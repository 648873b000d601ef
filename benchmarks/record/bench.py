"""The state one benchmark run shares across its modes, and how every mode is started: after the page pause,
on a quiet machine, and run again when other processes perturbed it."""
from __future__ import annotations

import argparse
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import yaml

from benchmarks.record.measure import machine_busy_seconds
from benchmarks.record.scenarios import Scenario


#: Deleting bags of this many bytes or more calls for the page pause before the next run (wait_for_fresh_pages).
PAGE_PAUSE_BYTES = 64 * 2**20


@dataclass
class Bench:
    args: argparse.Namespace
    workdir: Path
    node: Any  # the benchmark's own rclpy node: the service calls to the containers
    log: Callable[[str], None] = print
    counter: int = 0
    #: when the benchmark last deleted a big file (see wait_for_fresh_pages)
    last_free: float = 0.0
    #: the checkout the recorder containers run (None: this one) and their executor (None: --executor)
    code: Optional[Path] = None
    executor: Optional[str] = None

    def next_tag(self, scenario: Scenario, mode: str) -> str:
        self.counter += 1
        return f"{scenario.key.lower()}_{mode}_{self.counter}"

    def write_yaml(self, name: str, components: list[dict[str, Any]]) -> Path:
        """A ``--load`` start-up file in the work directory."""
        path = self.workdir / f"{name}.yaml"
        path.write_text(yaml.safe_dump({"components": components}, sort_keys=False))
        return path

    def discard_bags(self, *paths: Path) -> None:
        """Delete bag directories (unless --keep-bags) and, when they held :data:`PAGE_PAUSE_BYTES` or more, note
        when, for the page pause (a compressed recording's few MB free too few pages to matter)."""
        if not self.args.keep_bags:
            held = sum(file.stat().st_size for path in paths if path.is_dir()
                       for file in path.rglob("*") if file.is_file())
            for path in paths:
                shutil.rmtree(path, ignore_errors=True)
            if held >= PAGE_PAUSE_BYTES:
                self.last_free = time.monotonic()

    def wait_for_fresh_pages(self) -> None:
        """Wait until --page-pause s have passed since the benchmark last deleted a bag or ceiling file.

        Right after a big unlink, the kernel (of a virtual machine, at least) hands the freed page-cache pages
        to the next writer at a fraction of the cost of fresh ones (0.2 instead of ~1.5-2 CPU s/GB); after a
        few seconds they are gone. A recorder writing continuously gets fresh pages; without the pause,
        whichever mode runs after another would get cheaper writes.
        """
        remaining = self.args.page_pause - (time.monotonic() - self.last_free)
        if remaining > 0:
            time.sleep(remaining)

    def wait_for_quiet(self) -> tuple[float, float]:
        """Wait (up to --quiet-wait s) until other processes use less than --quiet-cpu CPUs; (waited s, load)."""
        started = time.monotonic()
        while True:
            busy0 = machine_busy_seconds()
            time.sleep(1.0)
            load = machine_busy_seconds() - busy0
            waited = time.monotonic() - started
            if load <= self.args.quiet_cpu or waited >= self.args.quiet_wait:
                return waited, load


def perturbed(result: dict[str, Any], args: argparse.Namespace) -> bool:
    """Other processes used more than --retry-cpu CPUs on average during the window."""
    window = result.get("window_s") or 0.0
    return window > 0 and (result.get("background_cpu_s") or 0.0) / window > args.retry_cpu


def summary(result: dict[str, Any]) -> str:
    """One log line of a finished run."""
    parts = []
    if "lost" in result:
        parts.append(f"lost {result['lost']}/{result['published']}, pub>={100 * result['min_pub_ratio']:.0f}%nom")
    if "mb_per_s" in result:
        parts.append(f"{result['mb_per_s']:.0f} MB/s")
    if "total_cpu_s" in result:
        parts.append(f"cpu {result['total_cpu_s']:.1f} s")
    if "background_cpu_s" in result:
        parts.append(f"other processes {result['background_cpu_s']:.1f} CPU s")
    return ", ".join(parts)


def guarded(bench: Bench, label: str, run: Callable[[], dict[str, Any]], retry: bool = True) -> dict[str, Any]:
    """Run one mode; a run perturbed by other processes is repeated (--retries) and the least perturbed kept.
    A mode that fails is reported as ``{"error": ...}``; the others still run."""
    attempts: list[dict[str, Any]] = []
    for attempt in range(1 + (bench.args.retries if retry else 0)):
        bench.wait_for_fresh_pages()
        waited, load = bench.wait_for_quiet() if bench.args.quiet_wait > 0 else (0.0, float("nan"))
        bench.log(f"[{time.strftime('%H:%M:%S')}] {label}{' (repeat: the last run was perturbed)' if attempt else ''}"
                  " ..." + (f" (waited {waited:.0f} s for other processes; machine load now {load:.2f} CPUs)"
                            if waited > 1.5 else ""))
        started = time.monotonic()
        try:
            result = run()
            result["quiet_wait_s"], result["load_before_cpus"] = waited, load
        except Exception as exc:  # noqa: BLE001 - one failed mode is reported, the others still run
            bench.log(f"    FAILED: {type(exc).__name__}: {exc}")
            if attempts:
                break
            return {"error": f"{type(exc).__name__}: {exc}"}
        bench.log(f"    done in {time.monotonic() - started:.0f} s: {summary(result)}")
        attempts.append(result)
        if not perturbed(result, bench.args):
            break
    best = min(attempts, key=lambda r: r.get("background_cpu_s") or 0.0)
    best["attempts"] = len(attempts)
    if len(attempts) > 1:
        best["other_attempts"] = [{k: r.get(k) for k in ("lost", "published", "mb_per_s", "total_cpu_s",
                                                          "background_cpu_s", "lossless")}
                                  for r in attempts if r is not best]
    return best
