#!/usr/bin/env python3
"""Recording benchmark: the zero-copy in-container recorder against DDS recording, on the same scenario.

    python benchmarks/record_bench.py [--quick] [--scenarios s1,s2,s3] [--modes ...] [--repeat N]
                                      [--baseline REV] [--json FILE|-] [--plot FILE] [--results DIR]

The implementation is the package ``benchmarks.record``; ``--help`` lists every option, benchmarks/README.md
says what each scenario and mode measures and what the targets are. The results go to a folder of their own
under benchmarks/results/.
"""
from __future__ import annotations

import sys

import isolation  # noqa: F401  (first: the ROS environment before rclpy is imported)

from benchmarks.record.main import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
