"""Where the benchmarks keep their result folders: below both benchmarks/result_folder.py, which writes them, and
benchmarks/report.py, which makes tables of them (each imports this, neither the other's constant)."""
from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
