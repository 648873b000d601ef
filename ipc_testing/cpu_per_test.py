"""A pytest plugin that writes the CPU time of every test, to find what makes a CPU-bound suite slow.

    python -m pytest -n 4 -p ipc_testing.cpu_per_test tests      # IPC_CPU_PER_TEST=DIR, default /tmp

Each worker appends one JSON line per test to ``DIR/cpu-per-test-<pid>.jsonl``: the test's id, the CPU seconds of
the worker itself during the test (its threads: in-process containers, probes), those of the child processes it
reaped meanwhile (container and command processes started and waited for by the test; a module's shared container
counts at the test that ends the module), and the wall seconds.
"""
from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: Any) -> Iterator[None]:
    before, started = os.times(), time.monotonic()
    yield
    after = os.times()
    line = {"id": item.nodeid, "wall": time.monotonic() - started,
            "cpu": after.user - before.user + after.system - before.system,
            "child": after.children_user - before.children_user + after.children_system - before.children_system}
    folder = Path(os.environ.get("IPC_CPU_PER_TEST") or "/tmp")
    with open(folder / f"cpu-per-test-{os.getpid()}.jsonl", "a") as out:
        out.write(json.dumps(line) + "\n")
