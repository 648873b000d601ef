"""The harness's command runner: a command that overruns its timeout is reported with what it printed so far and
where its threads were (native and Python stacks). ``subprocess.run`` dropped both: a fleet test's
``ipc-component record stop`` was killed after 60 s in a fresh-clone run with nothing to show why."""
from __future__ import annotations

import shutil
import sys

import pytest

from ipc_testing.process import run_command

STUCK = ("import sys, time\ndef waiting_here(): time.sleep(600)\n"
         "print('before', flush=True); print('err', file=sys.stderr, flush=True); waiting_here()")


def test_a_command_that_finishes_returns_its_output_and_status() -> None:
    done = run_command([sys.executable, "-c", "import sys; print('out'); print('err', file=sys.stderr); sys.exit(3)"],
                       30)
    assert (done.returncode, done.stdout, done.stderr) == (3, "out\n", "err\n")


def test_a_command_that_overruns_is_reported_with_its_output_and_stacks() -> None:
    with pytest.raises(AssertionError) as overran:
        run_command([sys.executable, "-c", STUCK], 2)
    report = str(overran.value)
    assert "did not finish within 2 s" in report and "--- stdout\nbefore\n" in report and "--- stderr\nerr\n" in report
    assert "in waiting_here" in report, report  # its Python stack
    assert ("#0 " if shutil.which("gdb") else "gdb is not installed") in report, report  # a frame, or why none
