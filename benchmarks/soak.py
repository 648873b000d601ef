#!/usr/bin/env python3
"""Soak benchmark: the S1 rig recorded for ``--minutes`` (30) while an extra driver is loaded and unloaded every
5 s, the recorder is handed over to a new one every minute and a player replays a bag in a loop into the
container: every message accounted for, every bag readable, the container's memory, file descriptors and
threads flat.

    python benchmarks/soak.py [--minutes 30] [--short] [--results DIR]

The implementation is the package ``benchmarks.endurance``; benchmarks/README.md says what is measured and how
it is judged. The results go to a folder of their own under benchmarks/results/ (``soak.json``). Exit status 1
when a bound failed.
"""
from __future__ import annotations

import sys

import isolation  # noqa: F401  (first: the ROS environment before rclpy is imported)

from benchmarks.endurance.main import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
