"""Record a real recording's file-system operations: a container process under ``strace -f``.

One container (``python -m component_container --use-intra-process-comms --load startup.yaml``) runs a camera
driver (small frames), an IMU driver and one recorder per configuration (MCAP and SQLite3, split and unsplit),
all intra-process, each writing its own bag under ``<workdir>/bags``. strace logs every file-system call of
the process with the bytes written (``-xx -s``: all strings in hex, never cut) and nanosecond wall-clock times;
the seccomp-bpf filter keeps the other system calls (DDS, timers) running at full speed. After ``seconds``
of recording the container gets SIGINT and finalizes every bag: those finished bags are the reference
(every message written, with its receive time as log time).
"""
from __future__ import annotations

import dataclasses
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

__all__ = ["CONFIGS", "Capture", "Config", "capture", "strace_command", "strace_usable", "trace_script"]

REPO = Path(__file__).resolve().parents[2]
TOPICS = ["/camera/image_raw", "/imu/imu"]
STRACE_CALLS = ("open,openat,openat2,creat,close,write,pwrite64,writev,pwritev,pwritev2,lseek,ftruncate,truncate,"
                "fsync,fdatasync,rename,renameat,renameat2,unlink,unlinkat,mkdir,mkdirat,rmdir,dup,dup2,dup3,"
                "fcntl,fallocate,link,linkat,sync,syncfs,clone,clone3,fork,vfork")
STRING_LIMIT = 64 * 1024 * 1024  # longer than any write of the recorder (1 MiB staging, in-place frames)


@dataclasses.dataclass(frozen=True)
class Config:
    """One recorder of the capture: its storage and split size (0: no splitting)."""

    name: str
    storage_id: str
    max_bagfile_size: int = 0


#: 1 MiB split size: with the default rig (~1.2 MB/s) a file every ~0.9 s, so a few splits in a few seconds.
CONFIGS = {
    config.name: config for config in (
        Config("mcap", "mcap"),
        Config("sqlite3", "sqlite3"),
        Config("mcap_split", "mcap", 1024 * 1024),
        Config("sqlite3_split", "sqlite3", 1024 * 1024),
    )
}


@dataclasses.dataclass
class Capture:
    """What a capture left: the log, the watched root (one bag per configuration) and the run's facts."""

    workdir: Path
    log: Path
    root: Path
    configs: list[Config]
    seconds: float
    wall: float  # how long the capture took, start to exit
    camera: tuple[int, int]
    exit_code: int

    def bag(self, config: Config | str) -> Path:
        return self.root / (config if isinstance(config, str) else config.name)


def strace_usable() -> str | None:
    """None if ``strace -f`` can trace a child here, else why not (no strace, ptrace refused)."""
    if shutil.which("strace") is None:
        return "strace is not installed"
    probe = subprocess.run(["strace", "-f", "-qq", "-e", "trace=none", "true"], capture_output=True, text=True,
                           timeout=30)
    if probe.returncode != 0:
        return f"strace cannot trace here: {probe.stderr.strip()[:200]}"
    return None


def strace_command(log: Path) -> list[str]:
    """The strace command line of a capture (followed by the program to trace)."""
    return ["strace", "-f", "--seccomp-bpf", "-qq", "--absolute-timestamps=format:unix,precision:ns", "-xx",
            "-s", str(STRING_LIMIT), "-e", f"trace={STRACE_CALLS}", "-e", "signal=none", "-o", str(log)]


def trace_script(workdir: Path, code: str, *args: str, timeout: float = 120.0) -> Path:
    """Run ``python -c code args...`` under the capture's strace in ``workdir``; return the log."""
    log = workdir / "strace.log"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    subprocess.run([*strace_command(log), sys.executable, "-c", code, *args], cwd=workdir, env=env, check=True,
                   timeout=timeout, capture_output=True)
    return log


def _startup(configs: list[Config], root: Path, camera: tuple[int, int], imu_rate: float) -> dict:
    components = [
        {"package": "components", "plugin": "components::CameraDriver", "name": "camera",
         "parameters": {"width": camera[0], "height": camera[1], "fps": 30.0},
         "extra_arguments": {"use_intra_process_comms": True}},
        {"package": "components", "plugin": "components::ImuDriver", "name": "imu",
         "parameters": {"rate": imu_rate}, "extra_arguments": {"use_intra_process_comms": True}},
    ]
    for config in configs:
        # storage.flush_interval and storage.sync_interval are left at their defaults (1 s each).
        components.append({
            "package": "components", "plugin": "components::Recorder", "name": f"recorder_{config.name}",
            "parameters": {"record": {"topics": TOPICS},
                           "storage": {"uri": str(root / config.name), "storage_id": config.storage_id,
                                       "max_bagfile_size": config.max_bagfile_size}},
            "extra_arguments": {"use_intra_process_comms": True}})
    return {"components": components}


def _children(pid: int) -> list[int]:
    children: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            children += [int(child) for child in (task / "children").read_text().split()]
        except OSError:
            pass
    return children


def _recording(bag: Path) -> bool:
    """The recorder has written messages: a storage file of at least a few KiB."""
    return bag.is_dir() and any(path.stat().st_size > 16384 for path in bag.iterdir()
                                if path.suffix in (".mcap", ".db3"))


def capture(workdir: Path, configs: list[Config], seconds: float = 4.0, camera: tuple[int, int] = (128, 96),
            imu_rate: float = 200.0, start_timeout: float = 60.0) -> Capture:
    """Run the container under strace, record ``seconds`` once every recorder writes, stop it with SIGINT."""
    workdir.mkdir(parents=True, exist_ok=True)
    root = workdir / "bags"
    root.mkdir()
    fd = os.open(root, os.O_RDONLY | os.O_DIRECTORY)  # the watched root is durable before the trace starts
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    startup = workdir / "startup.yaml"
    startup.write_text(yaml.safe_dump(_startup(configs, root, camera, imu_rate)))
    log = workdir / "strace.log"
    env = dict(os.environ)
    env.setdefault("ROS_DOMAIN_ID", str(random.randint(150, 230)))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    command = [*strace_command(log), sys.executable, "-m", "component_container", "--use-intra-process-comms",
               "--shutdown-timeout", "20", "--load", str(startup)]
    started = time.monotonic()
    output = open(workdir / "container.log", "wb")
    tracer = subprocess.Popen(command, cwd=workdir, env=env, stdout=output, stderr=subprocess.STDOUT,
                              start_new_session=True)
    container: int | None = None
    try:
        deadline = time.monotonic() + start_timeout
        while not all(_recording(root / config.name) for config in configs):
            if tracer.poll() is not None:
                raise RuntimeError(f"the container exited early ({tracer.returncode}):\n"
                                   + (workdir / "container.log").read_text()[-3000:])
            if time.monotonic() > deadline:
                raise RuntimeError("the recorders did not start writing within "
                                   f"{start_timeout} s:\n" + (workdir / "container.log").read_text()[-3000:])
            time.sleep(0.1)
        time.sleep(seconds)
        children = _children(tracer.pid)
        if len(children) != 1:
            raise RuntimeError(f"expected one traced container process, found {children}")
        container = children[0]
        os.kill(container, signal.SIGINT)  # the recorders finalize their bags
        exit_code = tracer.wait(timeout=60)
    finally:
        if tracer.poll() is None:
            if container is not None:
                try:
                    os.kill(container, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            tracer.kill()
            tracer.wait()
        output.close()
    return Capture(workdir, log, root, list(configs), seconds, time.monotonic() - started, camera, exit_code)
