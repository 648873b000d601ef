"""What a run measures from /proc: CPU time of processes, threads and the whole machine, dirty page cache, peak
RSS.

CPU of the machine outside the measured processes is split in two: other user processes (someone else's work
on a shared machine perturbs the numbers) and the kernel (its threads and interrupts: the writeback of the bag
itself among them, not charged to the recorder but competing for the same CPUs).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

CLK_TCK = os.sysconf("SC_CLK_TCK")
MB = 1e6
GB = 1e9
PF_KTHREAD = 0x00200000

#: machine busy seconds, and per process (CPU seconds, whether it is a kernel thread)
MachineSnapshot = tuple[float, dict[int, tuple[float, bool]]]


def stat_fields(path: str) -> list[str]:
    """The fields of a /proc stat file after the command name (which may hold spaces)."""
    with open(path) as stat:
        return stat.read().rsplit(")", 1)[1].split()


def cpu_times(pid: int) -> tuple[float, float]:
    """(utime, stime) of a process (all its threads), in seconds."""
    fields = stat_fields(f"/proc/{pid}/stat")
    return int(fields[11]) / CLK_TCK, int(fields[12]) / CLK_TCK


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (all its threads), in seconds."""
    return sum(cpu_times(pid))


def machine_identity() -> dict[str, str]:
    """The CPU model and kernel release: absolute CPU times compare only between runs on the same machine."""
    model = "unknown CPU"
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            model = next((line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("model name")), model)
    except OSError:
        pass
    return {"cpu_model": model, "kernel": os.uname().release}


def machine_busy_seconds() -> float:
    """CPU time all CPUs of the machine spent busy (user, nice, system, irq, softirq, steal), in seconds."""
    with open("/proc/stat") as stat:
        values = [int(v) for v in stat.readline().split()[1:9]]
    user, nice, system, _idle, _iowait, irq, softirq, steal = values
    return (user + nice + system + irq + softirq + steal) / CLK_TCK


def thread_cpu(pid: int) -> dict[int, tuple[str, float]]:
    """Per thread of a process: (name, utime + stime seconds). Python threads are all named 'python'."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            comm = (task / "comm").read_text().strip()
            fields = stat_fields(str(task / "stat"))
        except OSError:  # the thread ended meanwhile
            continue
        out[int(task.name)] = (comm, (int(fields[11]) + int(fields[12])) / CLK_TCK)
    return out


def thread_groups(before: dict[int, tuple[str, float]], after: dict[int, tuple[str, float]],
                  writer_tids: set[int]) -> dict[str, float]:
    """CPU seconds per thread group over an interval: the bag writer, other Python threads, Fast DDS threads."""
    groups: dict[str, float] = {}
    for tid, (comm, seconds) in after.items():
        spent = seconds - before.get(tid, (comm, 0.0))[1]
        group = ("bag writer" if tid in writer_tids else "python (executors, main)" if comm == "python"
                 else "fast-dds" if comm.startswith("dds.") else comm)
        groups[group] = groups.get(group, 0.0) + spent
    return {name: round(value, 3) for name, value in sorted(groups.items())}


def machine_snapshot() -> MachineSnapshot:
    """Machine busy seconds, and per process (all its threads) CPU seconds and whether it is a kernel thread."""
    busy = machine_busy_seconds()
    processes: dict[int, tuple[float, bool]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            fields = stat_fields(f"/proc/{entry}/stat")
        except OSError:
            continue
        processes[int(entry)] = ((int(fields[11]) + int(fields[12])) / CLK_TCK, bool(int(fields[6]) & PF_KTHREAD))
    return busy, processes


def other_cpu(before: MachineSnapshot, after: MachineSnapshot, ours: float, our_pids: set[int]
              ) -> tuple[float, float]:
    """(CPU s of other user processes, CPU s of the kernel: its threads, interrupts) between two snapshots.

    The kernel share includes the writeback of our own bags and, in a virtual machine, the I/O it causes.
    """
    user = 0.0
    for pid, (seconds, kernel) in after[1].items():
        if pid in our_pids or kernel:
            continue
        user += seconds - before[1].get(pid, (0.0, False))[0]
    total_other = max(0.0, after[0] - before[0] - ours)
    user = min(max(0.0, user), total_other)
    return user, total_other - user


@dataclass
class Sample:
    """One end of a measured window: the time, and the CPU of the measured processes and of the machine."""

    time_ns: int
    cpu: dict[str, tuple[float, float]]            # per process label: (utime, stime)
    threads: dict[str, dict[int, tuple[str, float]]]  # per process label: thread_cpu
    machine: MachineSnapshot

    @classmethod
    def take(cls, pids: dict[str, int]) -> "Sample":
        return cls(time.time_ns(), {label: cpu_times(pid) for label, pid in pids.items()},
                   {label: thread_cpu(pid) for label, pid in pids.items()}, machine_snapshot())


def window_cpu(start: Sample, end: Sample, pids: dict[str, int]) -> dict[str, object]:
    """CPU over the window between two samples: per process, its system part, the machine's other CPU."""
    cpu = {label: sum(end.cpu[label]) - sum(start.cpu[label]) for label in start.cpu}
    background, kernel = other_cpu(start.machine, end.machine, sum(cpu.values()), set(pids.values()) | {os.getpid()})
    return {"window_s": (end.time_ns - start.time_ns) / 1e9, "cpu_s": cpu, "total_cpu_s": sum(cpu.values()),
            "cpu_sys_s": {label: end.cpu[label][1] - start.cpu[label][1] for label in start.cpu},
            "background_cpu_s": background, "kernel_cpu_s": kernel}


def dirty_pages_mb() -> tuple[float, float]:
    """(dirty + under-writeback page cache, the kernel's dirty threshold) in MB, from /proc/vmstat."""
    values = {}
    with open("/proc/vmstat") as vmstat:
        for line in vmstat:
            name, _, value = line.partition(" ")
            values[name] = int(value)
    page_mb = os.sysconf("SC_PAGE_SIZE") / MB
    return ((values.get("nr_dirty", 0) + values.get("nr_writeback", 0)) * page_mb,
            values.get("nr_dirty_threshold", 0) * page_mb)


def sleep_watching_dirty(seconds: float) -> float:
    """Sleep, sampling the dirty page cache twice a second; returns its peak in MB."""
    deadline = time.monotonic() + seconds
    peak = dirty_pages_mb()[0]
    while (remaining := deadline - time.monotonic()) > 0:
        time.sleep(min(0.5, remaining))
        peak = max(peak, dirty_pages_mb()[0])
    return peak


def peak_rss_mb(pid: int) -> float:
    """VmHWM of a process, in MiB."""
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def source_skips(log: str) -> int:
    """Frames the drivers skipped at the source, as far as their (throttled) warnings tell."""
    total = 0
    for line in log.splitlines():
        if "cannot keep up" in line and "in total" in line:
            try:
                total += int(line.rsplit(",", 1)[1].split()[0])
            except (IndexError, ValueError):
                pass
    return total
