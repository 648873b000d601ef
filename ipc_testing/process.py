"""A container process started the way a user starts one, and stopped by its pid whatever happens."""
from __future__ import annotations

import contextlib
import ctypes
import fcntl
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO, Any

_LIBC = ctypes.CDLL(None, use_errno=True)
_SYS_TGKILL = 234  # x86_64


def stop_process(process: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 20.0) -> bool:
    """Signal ``process`` and wait; SIGKILL it if it does not exit within ``timeout``, after writing its threads'
    native stacks to stderr (a test's captured output). Returns whether it exited by itself (False: it had to be
    killed)."""
    if process.poll() is not None:
        return True
    process.send_signal(sig)
    try:
        process.wait(timeout=timeout)
        return True
    except subprocess.TimeoutExpired:
        print(native_stacks(process.pid), file=sys.stderr)
        process.kill()
        process.wait()
        return False


def signal_another_thread(pid: int, sig: int) -> int:
    """Give ``sig`` to a thread of process ``pid`` other than its main thread, one that does not block it
    (``tgkill``): what the kernel may do with any signal sent to the process. Returns that thread's id."""
    for task in sorted(Path(f"/proc/{pid}/task").iterdir(), key=lambda path: int(path.name)):
        blocked = int(next(line for line in (task / "status").read_text().splitlines()
                           if line.startswith("SigBlk:")).split()[1], 16)
        if int(task.name) != pid and not blocked & (1 << (sig - 1)):
            if _LIBC.syscall(_SYS_TGKILL, pid, int(task.name), sig) != 0:
                raise OSError(ctypes.get_errno(), f"tgkill({pid}, {task.name}, {sig}) failed")
            return int(task.name)
    raise LookupError(f"process {pid} has no thread besides its main one that takes signal {sig}")


def child_log(path: Path | None) -> IO[str]:
    """A file (``path``, or a temporary one) for a child process's output that this process reads while the
    child writes. Every write to it appends (O_APPEND): the child writes through the same open file description,
    whose offset :func:`read_log` moves; without it, a line written while this process was reading landed at that
    offset, over earlier output (a container's "Unloading" line vanished from its log so)."""
    log: IO[str] = (open(path, "w+", encoding="utf-8") if path is not None  # noqa: SIM115
                    else tempfile.TemporaryFile(mode="w+", prefix="container_", suffix=".log"))
    descriptor = log.fileno()
    fcntl.fcntl(descriptor, fcntl.F_SETFL, fcntl.fcntl(descriptor, fcntl.F_GETFL) | os.O_APPEND)
    return log


def read_log(log: IO[str]) -> str:
    """Everything written to a :func:`child_log` so far."""
    log.flush()
    log.seek(0)
    return log.read()


def native_stacks(pid: int) -> str:
    """Every thread's native stack of process ``pid`` (gdb), or why there are none: a process that ignores its
    signals is held in native code (Python runs signal handlers between bytecodes), where Python's own
    tracebacks do not reach."""
    gdb = shutil.which("gdb")
    if gdb is None:
        return f"no native stacks of {pid}: gdb is not installed"
    try:
        taken = subprocess.run([gdb, "-p", str(pid), "-batch", "-ex", "thread apply all bt 16"],
                               capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        return f"no native stacks of {pid}: gdb took over 60 s"
    return f"--- native stacks of {pid} (gdb):\n{taken.stdout}{taken.stderr}"


def run_command(argv: Sequence[str], timeout: float, env: Mapping[str, str] | None = None,
                **popen: Any) -> subprocess.CompletedProcess:
    """``subprocess.run(argv, capture_output=True, text=True, timeout=timeout)``, except that a command that
    overruns is not killed blind: the AssertionError names it with what it printed so far, its threads' native
    stacks (gdb) and their Python stacks (``PYTHONFAULTHANDLER``: SIGABRT makes a Python program print every
    thread's traceback, even one stuck in native code). ``subprocess.run`` loses all of it: its pipes' partial
    output is dropped with the process. The output goes through files, which hold whatever was written."""
    return run_commands([argv], timeout, env, **popen)[0]


def run_commands(commands: Sequence[Sequence[str]], timeout: float, env: Mapping[str, str] | None = None,
                 **popen: Any) -> list[subprocess.CompletedProcess]:
    """:func:`run_command` for several commands that run at the same time, all within ``timeout``; the first
    that overruns is reported, and the others are killed."""
    environment = dict(os.environ if env is None else env, PYTHONFAULTHANDLER="1")
    deadline = time.monotonic() + timeout
    with contextlib.ExitStack() as stack:
        logs = [(stack.enter_context(child_log(None)), stack.enter_context(child_log(None))) for _ in commands]
        processes = [subprocess.Popen(list(argv), stdout=out, stderr=err, text=True, env=environment, **popen)
                     for argv, (out, err) in zip(commands, logs)]
        for argv, process, (out, err) in zip(commands, processes, logs):
            try:
                process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                stacks = native_stacks(process.pid)
                stop_process(process, signal.SIGABRT, timeout=10)
                for other in processes:
                    if other.poll() is None:
                        other.kill()
                        other.wait()
                raise AssertionError(
                    f"{' '.join(argv)} did not finish within {timeout:g} s; its output so far (the Python stacks at "
                    f"its end):\n--- stdout\n{read_log(out)}--- stderr\n{read_log(err)}{stacks}") from None
        return [subprocess.CompletedProcess(process.args, process.returncode, read_log(out), read_log(err))
                for process, (out, err) in zip(processes, logs)]


class ContainerProcess:
    """``python -m component_container ARGS`` as a subprocess; a context manager that kills it on exit.

    * ``name``: the container node's name (``-r __node:=``); default ``ComponentManager``, as rclcpp's;
    * ``log_path``: where its output goes (default: a temporary file). A file, not a pipe: a pipe nobody reads
      fills up (64 KiB of log lines) and then blocks the container inside its logging calls;
    * ``fsize_limit``: start it under RLIMIT_FSIZE (SIGXFSZ ignored), so that writes beyond that size fail with
      EFBIG: a full disk for this process only;
    * ``code``: a source checkout whose packages it imports instead of the installed ones (PYTHONPATH);
    * ``env``: variables added to this process's environment;
    * ``prefix``: a command that execs the rest (``ip netns exec NS ...``), so the pid stays the container's.
    """

    def __init__(self, *args: str, name: str = "ComponentManager", cwd: str | Path | None = None,
                 log_path: Path | None = None, fsize_limit: int | None = None, code: Path | None = None,
                 env: Mapping[str, str] | None = None, prefix: Sequence[str] = ()) -> None:
        self.name = name if name.startswith("/") else f"/{name}"
        argv = ["component_container", *args]
        namespace, _, node = self.name.rpartition("/")
        if self.name != "/ComponentManager":
            argv += ["--ros-args", "-r", f"__node:={node}"]  # rcl takes several sections
        if namespace:
            argv += ["--ros-args", "-r", f"__ns:={namespace}"]
        self.log_path = log_path
        self._log = child_log(log_path)
        environment = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        if code is not None:
            environment["PYTHONPATH"] = os.pathsep.join(filter(None, (str(code), environment.get("PYTHONPATH"))))
        self.process = subprocess.Popen([*prefix, *_command(argv, fsize_limit)], stdout=self._log, stderr=subprocess.STDOUT,
                                        text=True, cwd=None if cwd is None else str(cwd), env=environment)

    @property
    def pid(self) -> int:
        return self.process.pid

    @property
    def returncode(self) -> int | None:
        return self.process.returncode

    @property
    def output(self) -> str:
        """Everything the container printed so far."""
        if self._log.closed:
            return self.log_path.read_text(errors="replace") if self.log_path is not None else ""
        return read_log(self._log)

    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0, check: bool = True) -> int:
        """Signal the container by pid and wait; kill it if it does not exit in time (an AssertionError with its
        output when ``check``). Returns the exit code."""
        if not stop_process(self.process, sig, timeout) and check:
            raise AssertionError(f"container {self.name} ({self.pid}) ignored signal {sig} for {timeout} s:\n"
                                 f"{self.output[-3000:]}")
        return self.process.returncode

    def kill(self) -> None:
        if self.alive():
            self.process.kill()
            self.process.wait()

    def __enter__(self) -> "ContainerProcess":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.kill()


def _command(argv: list[str], fsize_limit: int | None) -> list[str]:
    if fsize_limit is None:
        return [sys.executable, "-m", *argv]
    return [sys.executable, "-c",
            "import resource, runpy, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
            f"resource.setrlimit(resource.RLIMIT_FSIZE, ({fsize_limit}, {fsize_limit})); "
            f"sys.argv = {argv!r}; runpy.run_module('component_container', run_name='__main__')"]
