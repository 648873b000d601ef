"""The harness's log of a child process, read while the child writes: no line is lost. The child writes through
the same open file description as the reader, whose offset each read moves back to the start; without O_APPEND
its lines landed there, over earlier output (a container's "Unloading" line vanished from its log in a
fresh-clone run; 5,966 of 20,000 lines in this test on the code before)."""
from __future__ import annotations

import subprocess
import sys

from ipc_testing.process import child_log, read_log

LINES = 20000


def test_a_childs_output_read_while_it_writes_keeps_every_line() -> None:
    with child_log(None) as log:
        child = subprocess.Popen([sys.executable, "-c", f"for number in range({LINES}): print(number, flush=True)"],
                                 stdout=log, stderr=subprocess.STDOUT, text=True)
        reads = 0
        while child.poll() is None:
            read_log(log)
            reads += 1
        assert child.wait() == 0
        assert read_log(log).split() == [str(number) for number in range(LINES)], f"{reads} reads meanwhile"
