"""The benchmark's comparison with the previous result file (benchmarks/record/previous.py): which file is the
previous one, when a figure counts as worse, and the target row; on made-up records and on the repository's own
result files (no ROS)."""
from __future__ import annotations

import json
import pathlib
import shutil
from typing import Any

from benchmarks.record.previous import NOISE_FLOOR, compare, find_previous
from benchmarks.record.targets import Targets, previous_target

REPO = pathlib.Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
RIG = {"cameras": 2, "width": 1920, "height": 1080, "fps": 30.0, "lidar_points": 131072, "lidar_rate": 10.0,
       "imu_rate": 200.0, "storage": "mcap", "cache_mb": 100.0, "executor": "single"}


def mode(total_per_gb: float, recorder_per_gb: float | None = None) -> dict[str, Any]:
    return {"total_cpu_s_per_gb": total_per_gb, "recorder_cpu_s_per_gb": recorder_per_gb}


def record(started: str, ipc: float, dds: float = 2.0, drivers_cpu_s: float = 1.0, **config: Any) -> dict[str, Any]:
    return {"started_at": started, "git": {"commit": started[-2:]}, "command": "python benchmarks/record_bench.py",
            "config": {**RIG, **config},
            "S1": {"ipc": mode(ipc, ipc / 2), "dds": mode(dds, dds / 2),
                   "drivers": {"total_cpu_s": drivers_cpu_s, "window_s": 10.0}}}


def write(results: pathlib.Path, name: str, data: dict[str, Any]) -> None:
    (results / name).mkdir(parents=True)
    (results / name / "record.json").write_text(json.dumps(data))


def test_the_previous_file_is_the_newest_earlier_run_of_the_same_rig(tmp_path: pathlib.Path) -> None:
    write(tmp_path, "a", record("2026-01-01T10:00:01", 0.5))
    write(tmp_path, "b", record("2026-01-02T10:00:02", 0.6))
    write(tmp_path, "c", record("2026-01-03T10:00:03", 0.7, cameras=5))      # another rig
    write(tmp_path, "d", {**record("2026-01-03T10:00:04", 0.7), "S1": {"ipc": {"error": "failed"}}})
    write(tmp_path, "e", record("2026-01-09T10:00:05", 0.8))                # after this run
    found = find_previous(tmp_path, record("2026-01-05T10:00:00", 0.5))
    assert found is not None and found[0].parent.name == "b"
    assert find_previous(tmp_path, record("2026-01-01T09:00:00", 0.5)) is None


def test_worse_means_beyond_the_noise() -> None:
    changes = {c.name: c for c in compare(record("2", ipc=0.54, dds=3.0, drivers_cpu_s=1.0),
                                          record("1", ipc=0.50, dds=2.0, drivers_cpu_s=1.0))}
    assert not changes["ipc total CPU s/GB"].worse, "8 % is within the floor"
    assert changes["dds total CPU s/GB"].worse
    assert changes["ipc / dds CPU per GB"].previous == 0.25 and not changes["ipc / dds CPU per GB"].worse
    assert not changes["drivers-only CPU s/s"].worse
    assert all(change.noise == NOISE_FLOOR for change in changes.values())


def test_the_repeat_spread_is_the_noise() -> None:
    current = record("2", ipc=0.7)
    current["S1"]["repeat"] = {"results": [{"ipc": mode(value), "dds": mode(2.0)} for value in (0.5, 0.6, 0.8)]}
    change = next(c for c in compare(current, record("1", ipc=0.5)) if c.name == "ipc total CPU s/GB")
    assert change.noise == (0.8 - 0.5) / 0.6
    assert not change.worse, "+40 % is within the 50 % the repeats spread over"


def test_the_target_flags_the_regression_the_result_files_show(tmp_path: pathlib.Path) -> None:
    """fbed89f's S1 against 37991b3's, the result files where CPU per GB doubled unnoticed."""
    for name in ("2026-11-25-37991b3", "2026-11-27-fbed89f"):
        shutil.copytree(RESULTS / name, tmp_path / name)
    later = json.loads((tmp_path / "2026-11-27-fbed89f" / "record.json").read_text())
    targets = Targets()
    previous_target(later, tmp_path, targets)
    [row] = targets.rows
    assert row["result"] == "FAIL", row
    assert "ipc total CPU s/GB 1.13 vs 0.48" in row["detail"] and "2026-11-25-37991b3" in row["detail"]
    earlier = json.loads((tmp_path / "2026-11-25-37991b3" / "record.json").read_text())
    targets = Targets()
    previous_target(earlier, tmp_path, targets)
    assert targets.rows[0]["result"] == "N/A", "37991b3 has no earlier result in this folder"
