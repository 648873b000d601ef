"""Test-session isolation: every run gets its own ROS domain and never leaves loopback.

The variables are set at import time, before any test imports rclpy, so in-process nodes and the container
processes the tests start (which inherit the environment) all share the one private domain.
"""
from __future__ import annotations

import os
import random

os.environ["ROS_DOMAIN_ID"] = os.environ.get("IPC_TEST_DOMAIN_ID") or str(random.randint(1, 100))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.pop("ROS_STATIC_PEERS", None)
