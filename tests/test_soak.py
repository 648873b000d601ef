"""The soak benchmark's short run (``benchmarks/soak.py --short``, 14 s): the S1 rig's shape with small frames in
one container, an extra camera loaded and unloaded every 2 s, the recorder handed over every 3.5 s (three
recorders, splitting every 2 s), a player replaying a bag in a loop.

Checked from its report: every sequence number of every stream is in the union of the bags, no recorder
dropped anything or reported a loss, every bag is finalized and every file was read by baglib and, in full,
by rosbags; the container's open file descriptors and threads at the comparable moments of the last third
are at most a few above those of the first third (6 extra drivers loaded and unloaded in between: a
descriptor or a thread left behind by each would show), and it stops with exit status 0. The 30-minute run
with its fitted slopes is the benchmark's (docs/performance.md).

The accounting itself is checked on made-up bag contents: each kind of loss it must see.
"""
from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
from typing import Callable

import pytest

from benchmarks.endurance.accounting import Union, account
from benchmarks.endurance.bag_files import FileContent, runs_of

REPO = pathlib.Path(__file__).resolve().parents[1]
IMU = "/imu0/imu"
IMAGE, INFO = "/soak_extra/image_raw", "/soak_extra/camera_info"
REPLAY = "/soak_replay/chatter"
LOOP_NS = 5_000_000_000  # 50 messages at 10 Hz


def content(numbers: dict[tuple[str, str], list[int]], stamps: dict[tuple[str, str], list[int]] | None = None,
            replay: list[tuple[int, int]] | None = None) -> FileContent:
    """A file's content as the worker reports it."""
    return FileContent("f.mcap", 0, 0, {}, {}, {}, {stream: runs_of(values)[0] for stream, values in numbers.items()},
                       0, stamps or {}, replay or [], 0.0)


def clean_union() -> Union:
    """Two recorders: the IMU's 10 .. 99 (overlapping 50 .. 59), two extra instances with their camera infos, the
    player's 0 .. 49 once and 0 .. 9 again a loop later (the first ten recorded by both recorders)."""
    extra = {(IMAGE, "extra0"): [3, 4, 5], (IMAGE, "extra1"): [0, 1, 2]}
    stamps = {(IMAGE, "extra0"): [30, 40, 50], (INFO, "extra0"): [30, 40, 50],
              (IMAGE, "extra1"): [70, 80, 90], (INFO, "extra1"): [70, 80, 90]}
    played = [(n * 100_000_000, n) for n in range(50)] + [(LOOP_NS + n * 100_000_000, n) for n in range(10)]
    union = Union()
    union.add(0, content({(IMU, "imu0"): list(range(10, 60)), **extra}, stamps, played))
    union.add(1, content({(IMU, "imu0"): list(range(50, 100))}, replay=played[:10]))
    return union


def accounted(union: Union, published: int = 60) -> dict:
    return account(union, [IMU], 2, 50, LOOP_NS, published)


def test_accounting_of_a_complete_union() -> None:
    result = accounted(clean_union())
    assert result["lost"] == 0 and result["duplicates_in_one_bag"] == 0, result
    assert result["rig"][f"{IMU} (imu0)"]["before_first_recorder"] == 10
    assert result[REPLAY]["recorded"] == 60


@pytest.mark.parametrize(("case", "change"), [
    ("a rig number missing", lambda u: u.runs[(IMU, "imu0")].__setitem__(0, (10, 30))),  # 31 .. 49 gone
    ("an extra instance not from 0", lambda u: u.runs[(IMAGE, "extra1")].__setitem__(0, (1, 2))),
    ("an extra instance not recorded", lambda u: u.runs.pop((IMAGE, "extra1"))),
    ("a camera info missing", lambda u: u.stamps[(INFO, "extra1")].discard(80)),
    ("a player message missing", lambda u: u.replay.remove((LOOP_NS + 5 * 100_000_000, 5))),
    ("a number twice in one bag", lambda u: u.recorder_runs[1][(IMU, "imu0")].append((60, 61))),
])
def test_accounting_sees_each_kind_of_loss(case: str, change: Callable[[Union], object]) -> None:
    union = clean_union()
    change(union)
    result = accounted(union)
    assert result["lost"] > 0 or result["duplicates_in_one_bag"] > 0, (case, result)


def test_accounting_counts_the_players_publications() -> None:
    assert accounted(clean_union(), published=61)["lost"] == 1  # one publication no bag holds
    assert accounted(clean_union(), published=0)["lost"] > 0  # a player that never played


@pytest.mark.long
def test_short_soak_loses_nothing_and_leaves_nothing_behind(tmp_path: pathlib.Path) -> None:
    report_path = tmp_path / "soak.json"
    done = subprocess.run([sys.executable, str(REPO / "benchmarks" / "soak.py"), "--short", "--results", "",
                           "--output-dir", str(tmp_path), "--json", str(report_path)],
                          capture_output=True, text=True, timeout=120, cwd=REPO, env=dict(os.environ))
    assert report_path.exists(), done.stdout[-3000:] + done.stderr[-3000:]
    report = json.loads(report_path.read_text())
    verdicts = {line["bound"]: line for line in report["verdicts"]}
    failed = [line for line in report["verdicts"] if line["result"] == "FAIL"]
    assert not failed, (failed, report["problems"][:5])
    accounting = report["accounting"]
    assert accounting["lost"] == 0 and accounting["duplicates_in_one_bag"] == 0, accounting
    assert report["churn"]["extra_instances"] >= 5 and report["churn"]["recorders"] == 3, report["churn"]
    assert accounting["extra"]["recorded_messages"] > 0 and not accounting["extra"]["not_recorded"]
    assert accounting["/soak_replay/chatter"]["published"] > 0
    files = report["files"]
    assert files["count"] >= 3 * 2 and files["rosbags_read_messages"] == files["messages"] > 0, files
    assert all(bag["files"] and not bag["problems"] for bag in report["bags"]), report["bags"]
    for metric in ("fds", "threads"):
        line = next(line for name, line in verdicts.items() if name.startswith(f"{metric}:"))
        assert line["result"] == "PASS", line
    assert report["container"]["exit_status"] == 0 and done.returncode == 0, done.stderr[-3000:]
