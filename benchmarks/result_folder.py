"""Where a benchmark run's results go: ``benchmarks/results/<YYYY-MM-DD>-<short commit>/``, one folder per date
and commit measured, holding the JSON of each benchmark run there (``record.json``, ``replay.json``) and
``README.md``, the tables generated from them (benchmarks/report.py). A second run of the same benchmark on the
same day and commit gets a folder of its own (``...-2``, ``-3``, ...).
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.locations import REPO, RESULTS


def git_state() -> dict[str, Any]:
    """The commit measured and the files that differ from it (the containers run the working tree)."""
    def git(*command: str) -> str:
        try:
            return subprocess.run(["git", *command], cwd=REPO, capture_output=True, text=True, timeout=10).stdout
        except (OSError, subprocess.SubprocessError):
            return ""
    return {"commit": git("rev-parse", "--short", "HEAD").strip(),
            "modified": [line[3:] for line in git("status", "--porcelain", "--untracked-files=no").splitlines()]}


def add_location_arguments(parser: argparse.ArgumentParser) -> None:
    """``--dir`` (where a benchmark writes its bags) and ``--results`` (where its result folder goes)."""
    parser.add_argument("--dir", default="", help="where to write the bags (default: a temporary directory under "
                                                  "the repository, on the disk the results describe)")
    parser.add_argument("--results", default=str(RESULTS), help="the result folder goes under this directory ('': none)")


def work_directory(args: argparse.Namespace, prefix: str) -> tempfile.TemporaryDirectory:
    """A temporary directory for the bags, under ``--dir`` or the repository."""
    return tempfile.TemporaryDirectory(prefix=prefix, dir=Path(args.dir) if args.dir else REPO)


def add_run_arguments(parser: argparse.ArgumentParser, quick: str) -> None:
    """:func:`add_location_arguments` plus ``--quick`` (what ``quick`` says it shortens)."""
    add_location_arguments(parser)
    parser.add_argument("--quick", action="store_true", help=quick)


def run_header(script: str, argv: list[str]) -> dict[str, Any]:
    """What every result file says about its run first: the command, when it started (local time), the code."""
    return {"command": shlex.join(["python", f"benchmarks/{script}", *argv]),
            "started_at": time.strftime("%Y-%m-%dT%H:%M:%S"), "git": git_state()}


def run_environment() -> dict[str, Any]:
    """Where a benchmark of ROS processes runs: its domain, the CPUs, Python and the load average at its start."""
    return {"ros_domain_id": os.environ["ROS_DOMAIN_ID"], "cpus": os.cpu_count(), "python": sys.version.split()[0],
            "loadavg_start": os.getloadavg()}


def folder_for(results: Path, name: str, started_at: str, commit: str) -> Path:
    """The folder of a run started at ``started_at`` of ``commit``: the first of ``<date>-<commit>``,
    ``<date>-<commit>-2``, ... that does not hold a ``name``.json yet."""
    base = f"{started_at[:10]}-{commit or 'unknown'}"
    folder, number = results / base, 1
    while (folder / f"{name}.json").exists():
        number += 1
        folder = results / f"{base}-{number}"
    return folder


def save(report: dict[str, Any], name: str, results: Path = RESULTS) -> Path:
    """Write ``report`` as ``name``.json into its folder and regenerate the folder's tables; the folder."""
    from benchmarks.report import write_folder_tables
    folder = folder_for(results, name, report["started_at"], report["git"]["commit"])
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.json").write_text(json.dumps(report, indent=2, default=str) + "\n")
    write_folder_tables(folder)
    return folder
