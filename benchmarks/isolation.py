"""Imported first by the benchmark scripts that drive containers: every ROS run of theirs is isolated.

Sets a random ``ROS_DOMAIN_ID`` (unless one is set) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` before
rclpy is imported (the containers they start inherit both), and puts the repository (for ``benchmarks.*``)
and ``tests/`` (for the test helpers they share: container_process, fuzz_scene) on the path.
"""
from __future__ import annotations

import os
import pathlib
import random
import sys

if not os.environ.get("ROS_DOMAIN_ID"):
    os.environ["ROS_DOMAIN_ID"] = str(random.randint(1, 100))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path[1:1] = [str(REPO), str(REPO / "tests")]
