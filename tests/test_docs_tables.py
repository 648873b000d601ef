"""The tables of the documentation come from the benchmark result files, never from a hand.

benchmarks/report.py rewrites what stands between ``<!-- BEGIN GENERATED: NAME -->`` and
``<!-- END GENERATED: NAME -->`` from the newest result folder that holds table NAME. These tests run it as a
user does (a fresh process); none starts ROS.
"""
from __future__ import annotations

import json
import pathlib
import subprocess
import sys


REPO = pathlib.Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
HAND_TYPED = """# A page

Text before.

<!-- BEGIN GENERATED: s1 -->
| mode | lost |
|---|---|
| ipc | 0 (typed by hand) |
<!-- END GENERATED: s1 -->

Text after.
"""


def generator(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "benchmarks" / "report.py"), *args], capture_output=True,
                          text=True, timeout=120, cwd=REPO)


def newest_record() -> dict:
    """The newest record.json with S1 of the repository's result folders (runs of S2 or S3 alone have none)."""
    records = sorted((data for path in RESULTS.glob("*/record.json") if "S1" in (data := json.loads(path.read_text()))),
                     key=lambda data: data.get("started_at", ""))
    assert records, "no result folder with S1 in benchmarks/results"
    return records[-1]


def results_with(tmp_path: pathlib.Path, record: dict) -> pathlib.Path:
    folder = tmp_path / "results" / "2000-01-01-0000000"
    folder.mkdir(parents=True)
    (folder / "record.json").write_text(json.dumps(record))
    return folder.parent


def test_docs_tables_are_what_the_results_give() -> None:
    done = generator("--check")
    assert done.returncode == 0, f"the docs' tables differ from the result files:\n{done.stdout}{done.stderr}"


def test_a_table_edited_by_hand_is_rewritten(tmp_path: pathlib.Path) -> None:
    results = results_with(tmp_path, newest_record())
    doc = tmp_path / "page.md"
    doc.write_text(HAND_TYPED)
    check = generator("--check", "--results", str(results), "--docs", str(doc))
    assert check.returncode == 1 and "typed by hand" in check.stdout, check.stdout + check.stderr
    assert generator("--results", str(results), "--docs", str(doc)).returncode == 0
    text = doc.read_text()
    assert "typed by hand" not in text and "| ipc |" in text
    assert text.startswith("# A page\n\nText before.\n\n<!-- BEGIN GENERATED: s1 -->\n| mode |")
    assert text.endswith("<!-- END GENERATED: s1 -->\n\nText after.\n")
    assert generator("--check", "--results", str(results), "--docs", str(doc)).returncode == 0


def test_a_table_no_result_gives_is_left_with_a_message(tmp_path: pathlib.Path) -> None:
    record = {key: value for key, value in newest_record().items() if key != "S2"}
    results = results_with(tmp_path, record)
    doc = tmp_path / "page.md"
    doc.write_text(HAND_TYPED.replace("GENERATED: s1", "GENERATED: s2"))
    for mode in ((), ("--check",)):
        done = generator(*mode, "--results", str(results), "--docs", str(doc))
        assert done.returncode == 0, done.stdout + done.stderr
        assert "block 's2' left as it is: needs S2 in a record.json" in done.stderr
        assert "record_bench.py --scenarios s2" in done.stderr
        assert doc.read_text() == HAND_TYPED.replace("GENERATED: s1", "GENERATED: s2")
