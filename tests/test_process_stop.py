"""The harness's stop of a process that ignores its signal: killed, with its threads' native stacks written first
(where the Python tracebacks of a process held in native code do not reach)."""
from __future__ import annotations

import shutil
import signal
import subprocess
import sys

import pytest

from ipc_testing.process import stop_process

IGNORES_SIGINT = ("import signal, sys, time; signal.signal(signal.SIGINT, signal.SIG_IGN); "
                  "print('ready', flush=True); time.sleep(60)")


def test_a_process_that_ignores_its_signal_is_killed_after_its_native_stacks(
        capsys: pytest.CaptureFixture[str]) -> None:
    process = subprocess.Popen([sys.executable, "-c", IGNORES_SIGINT], stdout=subprocess.PIPE, text=True)
    try:
        assert process.stdout is not None and process.stdout.readline() == "ready\n"
        assert stop_process(process, signal.SIGINT, timeout=0.5) is False
        assert process.returncode == -signal.SIGKILL
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    written = capsys.readouterr().err
    if shutil.which("gdb"):
        assert f"native stacks of {process.pid} (gdb)" in written and "clock_nanosleep" in written, written
    else:
        assert f"no native stacks of {process.pid}: gdb is not installed" in written, written
