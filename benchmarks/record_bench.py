#!/usr/bin/env python3
"""Recording benchmark: the zero-copy in-container recorder against DDS recording, on the same scenario.

Usage: ``python benchmarks/record_bench.py [--quick] [--scenarios s1,s2,s3] [--repeat N] [--json FILE|-]
[--plot FILE]`` (``--help`` lists every knob). One run measures, for each scenario, these modes one after the other:

* ``ipc``: the drivers and ``components::Recorder`` in one container, every component loaded with
  ``extra_arguments: {use_intra_process_comms: true}`` (the recorder gets the drivers' message objects by
  reference and serializes them on its writer thread);
* ``dds``: the same drivers (same start-up file) in one container and the same recorder code in a second
  container process, loaded *without* intra-process, so every message crosses DDS as CDR
  (the architecture of ``ros2 bag record`` on Humble);
* ``drivers``: the drivers alone, no recorder (the sensors' own CPU cost);
* ``ceiling``: a plain Python loop writing the same number of bytes, in the same message sizes and order, to
  a file on the same filesystem as the bags (the write-speed limit of this machine in this run); the median
  of ``--ceiling-repeats`` runs; every run is listed, and a "warm" run reusing just-freed pages too.

Once per benchmark run, before the scenarios (unless ``--direct-mb 0``), the **direct-write limit** of the
filesystem the bags go to: ``--direct-mb`` MiB written with ``O_DIRECT`` (``baglib.write.direct_file``) in 8 MiB
page-aligned blocks of random bytes to a file in the bag directory, then fsync, then the file is deleted; the
median of ``--ceiling-repeats`` runs, each after the page pause. It bypasses the page cache, so it is the disk's
own sequential-write bandwidth (what ``dd oflag=direct`` reports), the physical limit a recorder can approach;
the buffered ceiling above is a Python write loop through the page cache, which may exceed it for a while.

``--repeat N`` runs S1's selected recorder modes (ipc, split, dds) N times back to back, each run exactly as a
single run (fresh processes, page pause, read-back); drivers and ceiling run once, after them. The tables show
run 1 in full, then a per-run table and the distribution per mode: lossless runs k of N, min / median / max
lost %, and per run the ratios ipc / dds of total CPU s/GB and split / ipc of the receive-to-write p99. Three
targets exist only with ``--repeat``: "ipc lossless in 5 of 5 consecutive runs" (evaluated when N >= 5; every
one of the N runs must be lossless), "ipc total CPU per GB <= 0.33 of dds in every run" (evaluated when dds
ran) and "split lossless, p99 <= 2x unsplit in every run" (when split ran).

``--baseline REV`` (S3) records S3 ipc once more with the code of git revision REV, checked out into a
temporary worktree that the container imports first (``PYTHONPATH``), with the single executor, right after the
current code's runs: the target "drivers + recorder CPU per message <= 1/2 of the baseline" compares the two
containers' whole CPU in the window per recorded message (issue 12's reference is 193a15f).

Every run (recorder modes, drivers, each ceiling and direct-write run) starts ``--page-pause`` s after the
benchmark last deleted a bag or file: on this kind of VM the kernel's cost of a buffered write depends
several-fold on whether its page-cache pages were freed moments ago (cheap) or are fresh (1.5-2 CPU s/GB, what
a continuously writing recorder gets), and without the pause whichever mode runs second would write for less.

Scenarios: S1 multi-camera rig (2x 1920x1080 rgb8 @ 30 Hz, LiDAR 131072 points @ 10 Hz, IMU @ 200 Hz, 10 s);
S2 ramp (1080p 30 Hz cameras added one at a time, on top of the S1 LiDAR and IMU unless ``--s2-base cameras``,
until a mode loses messages; largest lossless count per mode, cap 8); S3 ten IMU topics at 1 kHz each. Issue 12's
S2 targets are judged on the largest lossless ipc step: at least 5 cameras, and at least 85 % of the direct-write
limit measured in the same run (N/A when the ramp stopped at its cap without a loss below the target).

Measurement protocol of a recorder mode
---------------------------------------
1. start the container process(es) from generated ``--load`` start-up files; the recorder records an
   explicit topic list (``record.topics``) into ``<tmp>/<run>`` (MCAP by default, default 100 MiB cache);
2. warm-up: poll ``~/get_stats`` until every expected topic has received messages, then
   ``~/stop_recording`` (the warm-up bag is discarded) and ``~/start_recording`` (a fresh bag ``<run>_1``
   with fresh latency samples), and wait ``--settle`` seconds;
3. measured window ``[T0, T1]`` of ``--seconds``: /proc/<pid>/stat utime+stime of every process of the mode
   at T0 and T1, ``~/get_stats`` at T1 (write_latency_ms p50/p99, pooled over all topics, over the session's
   latest 20000 writes, i.e. the settle time plus the window);
4. ``--drain`` more seconds of recording (so the window's last messages have recorded successors), then
   ``~/stop_recording`` (flushes and finalizes); VmHWM of every process; SIGINT to every process (kill
   after a timeout), always, in ``finally`` blocks;
5. the bag is read back with rosbags (``rosbags.rosbag2.Reader``), never trusting the recorder's counters,
   and deleted.

Definitions
-----------
* window membership is by ``header.stamp`` (capture time, wall clock of this machine): T0 <= stamp <= T1;
* **published** (per topic with a sequence number: Image and PointCloud2 ``data[0:8]``, Imu
  ``orientation_covariance[1]``) = the driver's sequence numbers stamped inside the window: the recorded ones,
  plus every gap in the recorded sequence numbers (a message published and lost), whose stamp is interpolated
  between its recorded neighbours. Drivers number only the messages they publish (frames a late driver skips
  at the source consume no number), so this is the driver's own count of published messages over the window;
  only if nothing was recorded before T0 (or after T1) are the edge losses extrapolated at the nominal rate,
  and the row is marked ``~``. Zero loss is exact: it means no gap at all;
* CameraInfo has no sequence number: its published count is its image topic's (one CameraInfo per image,
  same stamp), its recorded count the CameraInfo messages stamped in the window;
* **recorded** = distinct sequence numbers stamped in the window found in the bag (duplicates are reported);
  **lost** = published - recorded; **pub%** = published / (nominal rate x window): below 100 % the drivers
  themselves could not keep their rate (source skips, not counted as lost but a failure to sustain the load);
* **MB/s** = serialized bytes of the window's recorded messages / window seconds (MB = 1e6 bytes,
  GB = 1e9 bytes); **% direct** = that MB/s as a percentage of the direct-write limit's MB/s (bytes over the
  time of the writes plus the final fsync) measured in the same benchmark run; **CPU s** = utime+stime over
  the window; **CPU s/GB** = that CPU / recorded GB;
* **recorder CPU** (``rec CPU s``): ``dds``: the recorder process; ``ipc``: ipc total minus drivers-only total
  for the same scenario (they share one process, so it includes the intra-process delivery and any
  contention). ``writer s`` is the CPU of the recorder's bag-writer thread alone (the thread that appears
  when ``~/start_recording`` opens the measured bag); the intake callbacks run on the executor thread. The
  subtraction is not additive in practice (rclpy's executor costs less per callback when it is busier), so
  when it comes out below the writer thread's CPU the targets use the writer thread's CPU instead;
* **kernel s** / **other s**: CPU the machine spent during the window outside the mode's processes (from
  /proc/stat and /proc/*/stat): kernel threads and interrupts (the writeback of the bag itself among them:
  not charged to the recorder, but it competes for the same 2 CPUs), and other people's processes on a
  shared machine. Before each mode the benchmark waits up to ``--quiet-wait`` s for the machine to go below
  ``--quiet-cpu`` busy CPUs, and repeats a run where other processes used more than ``--retry-cpu``;
* **peak RSS** = VmHWM of each process at the end of the run (after finalization), i.e. over its whole life;
* a step of S2 is **lossless** when no topic lost a message *and* every topic published >= 97 % of nominal.

Environment: ``ROS_DOMAIN_ID`` is set to a random 1..100 when unset and ``ROS_AUTOMATIC_DISCOVERY_RANGE`` to
LOCALHOST before anything starts. Bags and the ceiling and direct-write files go to a temporary directory under
``--output-dir`` (default: the current directory), removed at the end.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import mmap
import os
import random
import shutil
import signal
import statistics
import struct
import subprocess
import sys
import tempfile
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import yaml

CLK_TCK = os.sysconf("SC_CLK_TCK")
DEFAULT_CACHE = 100 * 1024 * 1024  # rosbag2's storage.max_cache_size default
MB = 1e6
GB = 1e9
PUBLISH_RATE_OK = 0.97  # a driver that published less than this share of its nominal rate did not keep up
DIRECT_BLOCK = 8 * 1024 * 1024  # bytes per O_DIRECT write of the direct-write limit (a multiple of every block size)
S2_TARGET_CAMERAS = 5  # issue 12: ipc lossless with 5 cameras (about 0.96 GB/s with the LiDAR and IMU) ...
S2_TARGET_DIRECT_PCT = 85  # ... i.e. at >= 85 % of the direct-write limit measured in the same run

CEILING_WORKER = textwrap.dedent("""
    import json, os, sys, time
    spec = json.load(open(sys.argv[1]))
    sizes = spec["sizes"]
    buffer = memoryview(os.urandom(max(sizes)))
    cpu0, t0 = time.process_time(), time.perf_counter()
    with open(spec["path"], "wb") as out:
        for size in sizes:
            out.write(buffer[:size])
    t1, cpu1 = time.perf_counter(), time.process_time()
    fd = os.open(spec["path"], os.O_RDONLY)
    os.fsync(fd)
    os.close(fd)
    t2 = time.perf_counter()
    print(json.dumps({"seconds": t1 - t0, "cpu_s": cpu1 - cpu0, "fsync_s": t2 - t1, "bytes": sum(sizes)}))
""")


# ----------------------------------------------------------------------------------------------- scenarios
@dataclass
class TopicSpec:
    name: str
    type_name: str
    kind: str  # image | camera_info | cloud | imu
    rate: float
    size: int = 0  # serialized CDR bytes of one message
    image_topic: str = ""  # camera_info: its image topic


@dataclass
class Scenario:
    key: str
    title: str
    seconds: float
    cameras: int = 0
    width: int = 1920
    height: int = 1080
    fps: float = 30.0
    lidar_points: int = 0  # 0: no lidar
    lidar_rate: float = 10.0
    imus: int = 0
    imu_rate: float = 200.0

    def describe(self) -> str:
        parts = []
        if self.cameras:
            parts.append(f"{self.cameras}x camera {self.width}x{self.height} rgb8 @ {self.fps:g} Hz")
        if self.lidar_points:
            parts.append(f"lidar {self.lidar_points} pts @ {self.lidar_rate:g} Hz")
        if self.imus:
            parts.append(f"{self.imus}x IMU @ {self.imu_rate:g} Hz")
        return ", ".join(parts) + f"; {self.seconds:g} s window"

    def components(self) -> list[dict[str, Any]]:
        ipc = {"use_intra_process_comms": True}
        out: list[dict[str, Any]] = []
        for i in range(self.cameras):
            out.append({"package": "components", "plugin": "components::CameraDriver", "name": f"cam{i}",
                        "parameters": {"width": self.width, "height": self.height, "fps": float(self.fps),
                                       "encoding": "rgb8", "frame_id": f"cam{i}"},
                        "extra_arguments": dict(ipc)})
        if self.lidar_points:
            out.append({"package": "components", "plugin": "components::LidarDriver", "name": "lidar",
                        "parameters": {"points_per_scan": self.lidar_points, "rate": float(self.lidar_rate)},
                        "extra_arguments": dict(ipc)})
        for i in range(self.imus):
            out.append({"package": "components", "plugin": "components::ImuDriver", "name": f"imu{i}",
                        "parameters": {"rate": float(self.imu_rate), "frame_id": f"imu{i}"},
                        "extra_arguments": dict(ipc)})
        return out

    def topics(self) -> dict[str, TopicSpec]:
        specs: list[TopicSpec] = []
        for i in range(self.cameras):
            specs.append(TopicSpec(f"/cam{i}/image_raw", "sensor_msgs/msg/Image", "image", self.fps))
            specs.append(TopicSpec(f"/cam{i}/camera_info", "sensor_msgs/msg/CameraInfo", "camera_info", self.fps,
                                   image_topic=f"/cam{i}/image_raw"))
        if self.lidar_points:
            specs.append(TopicSpec("/lidar/points", "sensor_msgs/msg/PointCloud2", "cloud", self.lidar_rate))
        for i in range(self.imus):
            specs.append(TopicSpec(f"/imu{i}/imu", "sensor_msgs/msg/Imu", "imu", self.imu_rate))
        for spec in specs:
            spec.size = serialized_size(self, spec)
        return {spec.name: spec for spec in specs}


_SIZE_CACHE: dict[tuple, int] = {}


def serialized_size(scenario: Scenario, spec: TopicSpec) -> int:
    """CDR size of one message of the topic, by serializing a sample like the driver's."""
    frame_id = spec.name.split("/")[1]
    key = (spec.kind, frame_id, scenario.width, scenario.height, scenario.lidar_points)
    if key not in _SIZE_CACHE:
        from rclpy.serialization import serialize_message
        from sensor_msgs.msg import CameraInfo, Image, Imu, PointCloud2, PointField
        from std_msgs.msg import Header
        header = Header(frame_id=frame_id)
        if spec.kind == "image":
            msg: Any = Image(header=header, height=scenario.height, width=scenario.width, encoding="rgb8",
                             step=scenario.width * 3)
            msg.data = bytes(scenario.width * scenario.height * 3)
        elif spec.kind == "camera_info":
            msg = CameraInfo(header=header, height=scenario.height, width=scenario.width,
                             distortion_model="plumb_bob", d=[0.0] * 5)
        elif spec.kind == "cloud":
            msg = PointCloud2(header=header, height=1, width=scenario.lidar_points, point_step=24,
                              row_step=24 * scenario.lidar_points, is_dense=True,
                              fields=[PointField(name=n, offset=o, datatype=7 if n != "ring" else 4, count=1)
                                      for n, o in (("x", 0), ("y", 4), ("z", 8), ("intensity", 12),
                                                   ("ring", 16), ("time", 20))])
            msg.data = bytes(24 * scenario.lidar_points)
        else:
            msg = Imu(header=header)
        _SIZE_CACHE[key] = len(serialize_message(msg))
    return _SIZE_CACHE[key]


def s1_scenario(args: argparse.Namespace) -> Scenario:
    return Scenario("S1", "S1 multi-camera rig", args.seconds, cameras=args.cameras, width=args.width,
                    height=args.height, fps=args.fps, lidar_points=args.lidar_points, lidar_rate=args.lidar_rate,
                    imus=1, imu_rate=args.imu_rate)


def s2_scenario(args: argparse.Namespace, cameras: int) -> Scenario:
    rig = args.s2_base == "rig"
    return Scenario("S2", f"S2 ramp, {cameras} camera(s)", args.s2_seconds, cameras=cameras, width=args.width,
                    height=args.height, fps=args.fps, lidar_points=args.lidar_points if rig else 0,
                    lidar_rate=args.lidar_rate, imus=1 if rig else 0, imu_rate=args.imu_rate)


def s3_scenario(args: argparse.Namespace) -> Scenario:
    return Scenario("S3", "S3 IMU storm", args.s3_seconds, imus=args.s3_imus, imu_rate=args.s3_rate)


# ----------------------------------------------------------------------------------------------- processes
def cpu_times(pid: int) -> tuple[float, float]:
    """(utime, stime) of a process (all its threads), in seconds."""
    with open(f"/proc/{pid}/stat") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
    return int(fields[11]) / CLK_TCK, int(fields[12]) / CLK_TCK


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (all its threads), in seconds."""
    return sum(cpu_times(pid))


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
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
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


PF_KTHREAD = 0x00200000


def machine_snapshot() -> tuple[float, dict[int, tuple[float, bool]]]:
    """Machine busy seconds, and per process (all its threads) CPU seconds and whether it is a kernel thread."""
    busy = machine_busy_seconds()
    processes: dict[int, tuple[float, bool]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as stat:
                fields = stat.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        processes[int(entry)] = ((int(fields[11]) + int(fields[12])) / CLK_TCK, bool(int(fields[6]) & PF_KTHREAD))
    return busy, processes


def other_cpu(before: tuple[float, dict[int, tuple[float, bool]]], after: tuple[float, dict[int, tuple[float, bool]]],
              ours: float, our_pids: set[int]) -> tuple[float, float]:
    """(CPU s of other user processes, CPU s of the kernel: its threads, interrupts) between two snapshots.

    The kernel share includes the writeback of our own bags and, in a VM, the I/O it causes.
    """
    user = 0.0
    for pid, (seconds, kernel) in after[1].items():
        if pid in our_pids or kernel:
            continue
        user += seconds - before[1].get(pid, (0.0, False))[0]
    total_other = max(0.0, after[0] - before[0] - ours)
    user = min(max(0.0, user), total_other)
    return user, total_other - user


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
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


class Container:
    """``python -m component_container`` as a subprocess, output to a log file, stopped by its pid."""

    def __init__(self, label: str, node_name: str, load_files: list[Path], log_path: Path, executor: str,
                 threads: int, cwd: Path, code: Optional[Path] = None) -> None:
        """``code``: a checkout whose packages the container imports instead of this one's (--baseline)."""
        self.label = label
        self.node_name = node_name
        self.log_path = log_path
        command = [sys.executable, "-m", "component_container", "--executor", executor]
        for path in load_files:
            command += ["--load", str(path)]
        command += ["--ros-args", "-r", f"__node:={node_name}"]
        if executor == "multi":
            command += ["-p", f"thread_num:={threads}"]
        self._log = open(log_path, "w")
        env = dict(os.environ)
        if code is not None:
            env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(code), env.get("PYTHONPATH"))))
        self.process = subprocess.Popen(command, stdout=self._log, stderr=subprocess.STDOUT, cwd=str(cwd), env=env)
        self.pid = self.process.pid

    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self, timeout: float = 30.0) -> Optional[int]:
        """SIGINT, then SIGKILL after ``timeout``; returns the exit code."""
        try:
            if self.alive():
                self.process.send_signal(signal.SIGINT)
                try:
                    self.process.wait(timeout=timeout)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait(timeout=10)
            return self.process.returncode
        finally:
            self._log.close()

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""


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


# ----------------------------------------------------------------------------------------------- ROS client
class RosClient:
    """The benchmark's own node: Trigger calls to the recorder and the container's ListNodes."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        rclpy.init(args=["record_bench"])
        self._rclpy = rclpy
        self.node = rclpy.create_node(f"record_bench_{os.getpid()}")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown()

    def trigger(self, service: str) -> Any:
        from std_srvs.srv import Trigger
        return self.node.create_client(Trigger, service)

    def call(self, client: Any, request: Any = None, timeout: float = 60.0) -> Any:
        if request is None:
            request = client.srv_type.Request()
        future = client.call_async(request)
        self.executor.spin_until_future_complete(future, timeout_sec=timeout)
        if not future.done():
            client.remove_pending_request(future)
            raise TimeoutError(f"no reply from {client.srv_name} within {timeout:g} s")
        return future.result()

    def query(self, client: Any, timeout: float = 60.0) -> Any:
        """An idempotent call (``~/get_stats``), sent again until a reply arrives: Fast DDS drops the reply to
        a client whose reply reader the server has not matched yet. Sent once, two of five dds runs of one
        ``--repeat 5`` (2026-11-23) got no reply within 60 s and lost their results."""
        from ipc_component.repeated_call import RepeatedCall
        call = RepeatedCall(client, client.srv_type.Request)
        deadline = time.monotonic() + timeout
        try:
            while call.reply is None:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"no reply from {client.srv_name} within {timeout:g} s")
                call.step(time.monotonic())
                self.executor.spin_once(timeout_sec=0.02)
            return call.reply
        finally:
            call.close()

    def wait_for(self, client: Any, deadline: float, alive: Callable[[], bool]) -> None:
        while not client.wait_for_service(timeout_sec=0.5):
            if not alive():
                raise RuntimeError(f"a container exited before {client.srv_name} appeared")
            if time.monotonic() > deadline:
                raise TimeoutError(f"{client.srv_name} did not appear")

    def destroy(self, client: Any) -> None:
        self.node.destroy_client(client)


# ----------------------------------------------------------------------------------------------- bag read-back
def _seq_reader(spec: TopicSpec, scenario: Scenario) -> Callable[[bytes], Optional[int]]:
    """Fast sequence-number extraction from CDR (checked against rosbags deserialization on first use)."""
    if spec.kind == "image":
        n = scenario.width * scenario.height * 3
        def image(raw: bytes) -> int:  # data is the last field
            assert struct.unpack_from("<I", raw, len(raw) - n - 4)[0] == n, "unexpected Image layout"
            return int.from_bytes(raw[len(raw) - n:len(raw) - n + 8], "little")
        return image
    if spec.kind == "cloud":
        n = 24 * scenario.lidar_points
        def cloud(raw: bytes) -> int:  # data, then is_dense (1 byte)
            assert struct.unpack_from("<I", raw, len(raw) - n - 5)[0] == n, "unexpected PointCloud2 layout"
            return int.from_bytes(raw[len(raw) - n - 1:len(raw) - n + 7], "little")
        return cloud
    if spec.kind == "imu":
        def imu(raw: bytes) -> int:  # header (stamp, frame_id), quaternion, orientation_covariance[0..8]
            frame_len = struct.unpack_from("<I", raw, 4 + 8)[0]
            offset = 8 + 4 + frame_len
            offset = (offset + 7) // 8 * 8 + 32 + 8
            return int(struct.unpack_from("<d", raw, 4 + offset)[0])
        return imu
    return lambda raw: None


def _seq_by_rosbags(typestore: Any, raw: bytes, spec: TopicSpec) -> Optional[int]:
    msg = typestore.deserialize_cdr(raw, spec.type_name)
    if spec.kind in ("image", "cloud"):
        return int.from_bytes(bytes(msg.data[:8]), "little")
    if spec.kind == "imu":
        return int(msg.orientation_covariance[1])
    return None


def read_bag(path: Path, scenario: Scenario, topics: dict[str, TopicSpec]) -> dict[str, Any]:
    """Every message of the bag: per topic a list of (sequence or None, stamp ns, size)."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    typestore = get_typestore(Stores.ROS2_JAZZY)
    readers = {name: _seq_reader(spec, scenario) for name, spec in topics.items()}
    checked: set[str] = set()
    records: dict[str, list[tuple[Optional[int], int, int]]] = {name: [] for name in topics}
    unexpected = 0
    with Reader(path) as reader:
        for connection, _, raw in reader.messages():
            spec = topics.get(connection.topic)
            if spec is None:
                unexpected += 1
                continue
            assert raw[1] == 1, "only little-endian CDR is expected"
            sec, nanosec = struct.unpack_from("<iI", raw, 4)
            seq = readers[spec.name](raw)
            if spec.name not in checked:
                expected = _seq_by_rosbags(typestore, raw, spec)
                if expected != seq:
                    raise AssertionError(f"{spec.name}: sequence parser says {seq}, rosbags says {expected}")
                checked.add(spec.name)
            records[spec.name].append((seq, sec * 1_000_000_000 + nanosec, len(raw)))
        total = reader.message_count
    return {"records": records, "unexpected": unexpected, "metadata_count": total}


def published_in_window(recs: list[tuple[Optional[int], int, int]], t0: int, t1: int,
                        rate: float) -> tuple[int, bool]:
    """How many sequence numbers the driver published with a stamp in [t0, t1]; (count, estimated at an edge).

    Recorded messages count with their stamps. A gap in the sequence numbers is a lost message whose stamp is
    interpolated between the recorded neighbours. Before the first / after the last recorded message, lost
    messages are extrapolated at the nominal rate (then the count is marked estimated).
    """
    unique: dict[int, int] = {}
    for seq, stamp, _ in recs:
        unique.setdefault(seq, stamp)
    points = sorted(unique.items())
    if not points:
        return round((t1 - t0) / 1e9 * rate), True
    count = sum(1 for _, stamp in points if t0 <= stamp <= t1)
    for (a, ta), (b, tb) in zip(points, points[1:]):
        if b - a > 1 and tb >= t0 and ta <= t1:
            step = (tb - ta) / (b - a)
            count += sum(1 for k in range(1, b - a) if t0 <= ta + k * step <= t1)
    estimated = False
    first_stamp, last_stamp = points[0][1], points[-1][1]
    if first_stamp > t0:  # nothing recorded before the window: extrapolate back at the nominal rate
        count += int((min(first_stamp, t1) - t0) / 1e9 * rate)
        estimated = True
    if last_stamp < t1:  # nothing recorded after the window
        count += int((t1 - max(last_stamp, t0)) / 1e9 * rate)
        estimated = True
    return count, estimated


def window_counts(records: dict[str, list[tuple[Optional[int], int, int]]], topics: dict[str, TopicSpec],
                  t0: int, t1: int) -> dict[str, dict[str, Any]]:
    """published / recorded / lost per topic over the window (see the module docstring)."""
    window_s = (t1 - t0) / 1e9
    out: dict[str, dict[str, Any]] = {}
    for name, spec in topics.items():
        if spec.kind == "camera_info":
            continue
        recs = sorted(records.get(name, []))
        in_window = [r for r in recs if t0 <= r[1] <= t1]
        seqs = {r[0] for r in in_window}
        published, estimated = published_in_window(recs, t0, t1, spec.rate)
        published = max(published, len(seqs))
        out[name] = {"published": published, "recorded": len(seqs), "duplicates": len(in_window) - len(seqs),
                     "bytes": sum(r[2] for r in in_window), "estimated": estimated,
                     "nominal": window_s * spec.rate}
    for name, spec in topics.items():
        if spec.kind != "camera_info":
            continue
        image = out[spec.image_topic]
        in_window = [r for r in records.get(name, []) if t0 <= r[1] <= t1]
        stamps = {r[1] for r in in_window}
        out[name] = {"published": image["published"], "recorded": len(stamps),
                     "duplicates": len(in_window) - len(stamps), "bytes": sum(r[2] for r in in_window),
                     "estimated": image["estimated"], "nominal": window_s * spec.rate}
    for entry in out.values():
        entry["lost"] = max(0, entry["published"] - entry["recorded"])
        entry["pub_ratio"] = entry["published"] / entry["nominal"] if entry["nominal"] else float("nan")
    return {name: out[name] for name in topics}


# ----------------------------------------------------------------------------------------------- runs
@dataclass
class Bench:
    args: argparse.Namespace
    workdir: Path
    ros: RosClient
    counter: int = 0
    log: Callable[[str], None] = print
    #: when the benchmark last deleted a big file (see wait_for_fresh_pages)
    last_free: float = 0.0
    #: the checkout the recorder containers run (None: this one) and their executor (None: --executor)
    code: Optional[Path] = None
    executor: Optional[str] = None

    def next_tag(self, scenario: Scenario, mode: str) -> str:
        self.counter += 1
        return f"{scenario.key.lower()}_{mode}_{self.counter}"

    def write_yaml(self, name: str, components: list[dict[str, Any]]) -> Path:
        path = self.workdir / f"{name}.yaml"
        path.write_text(yaml.safe_dump({"components": components}, sort_keys=False))
        return path


#: The recorder modes: ipc, ipc splitting its files every --split-mb MiB, and dds.
RECORDER_MODES = ("ipc", "split", "dds")
IPC_MODES = ("ipc", "split")  # the modes that record in the drivers' process


def recorder_component(name: str, topics: list[str], uri: Path, args: argparse.Namespace,
                       intra_process: bool, split_bytes: int = 0) -> dict[str, Any]:
    return {"package": "components", "plugin": "components::Recorder", "name": name,
            "parameters": {"record": {"topics": topics},
                           "storage": {"uri": str(uri), "storage_id": args.storage,
                                       "max_cache_size": int(args.cache_mb * 1024 * 1024),
                                       "max_bagfile_size": split_bytes}},
            "extra_arguments": {"use_intra_process_comms": intra_process}}


def run_recorder_mode(bench: Bench, scenario: Scenario, mode: str) -> dict[str, Any]:
    """``ipc`` or ``dds`` on one scenario; see the module docstring for the protocol."""
    args = bench.args
    tag = bench.next_tag(scenario, mode)
    topics = scenario.topics()
    uri = bench.workdir / tag
    recorder_name = f"rec_{tag}"
    drivers = scenario.components()
    in_process = mode in ("ipc", "split")
    recorder = recorder_component(recorder_name, list(topics), uri, args, intra_process=in_process,
                                  split_bytes=int(args.split_mb * 1024 * 1024) if mode == "split" else 0)
    containers: list[Container] = []
    clients: list[Any] = []
    result: dict[str, Any] = {"mode": mode, "scenario": scenario.key, "cameras": scenario.cameras}
    try:
        if in_process:
            files = [bench.write_yaml(f"{tag}_drivers", drivers), bench.write_yaml(f"{tag}_recorder", [recorder])]
            containers.append(Container(mode, f"bench_{tag}", files, bench.workdir / f"{tag}.log",
                                        bench.executor or args.executor, args.threads, bench.workdir, bench.code))
            recorder_proc = containers[0]
        else:
            containers.append(Container("drivers", f"bench_{tag}_drivers",
                                        [bench.write_yaml(f"{tag}_drivers", drivers)],
                                        bench.workdir / f"{tag}_drivers.log", args.executor, args.threads,
                                        bench.workdir))
            containers.append(Container("recorder", f"bench_{tag}_recorder",
                                        [bench.write_yaml(f"{tag}_recorder", [recorder])],
                                        bench.workdir / f"{tag}_recorder.log", args.executor, args.threads,
                                        bench.workdir))
            recorder_proc = containers[1]
        alive = lambda: all(c.alive() for c in containers)  # noqa: E731
        get_stats = bench.ros.trigger(f"/{recorder_name}/get_stats")
        stop = bench.ros.trigger(f"/{recorder_name}/stop_recording")
        start = bench.ros.trigger(f"/{recorder_name}/start_recording")
        clients += [get_stats, stop, start]
        started = time.monotonic()
        deadline = started + args.startup_timeout
        for client in clients:
            bench.ros.wait_for(client, deadline, alive)
        while True:  # warm-up: every expected topic subscribed and flowing
            stats = json.loads(bench.ros.query(get_stats).message)
            current = (stats.get("current") or {}).get("topics", {})
            missing = [t for t in topics if current.get(t, {}).get("received", 0) == 0]
            if not missing:
                break
            if not alive():
                raise RuntimeError("a container exited during warm-up")
            if time.monotonic() > deadline:
                raise TimeoutError(f"topics never reached the recorder: {', '.join(missing)}")
            time.sleep(0.2)
        result["warmup_s"] = time.monotonic() - started
        threads_before = set(thread_cpu(recorder_proc.pid))
        reply = bench.ros.call(stop)
        if not reply.success:
            raise RuntimeError(f"stop_recording (warm-up bag) failed: {reply.message}")
        reply = bench.ros.call(start)
        if not reply.success:
            raise RuntimeError(f"start_recording failed: {reply.message}")
        # the new session's writer thread is the thread that did not exist before the restart
        writer_tids = set(thread_cpu(recorder_proc.pid)) - threads_before
        time.sleep(args.settle)

        t0 = time.time_ns()
        cpu0 = {c.label: cpu_times(c.pid) for c in containers}
        threads0 = {c.label: thread_cpu(c.pid) for c in containers}
        machine0 = machine_snapshot()
        peak_dirty = sleep_watching_dirty(scenario.seconds)
        t1 = time.time_ns()
        cpu1 = {c.label: cpu_times(c.pid) for c in containers}
        threads1 = {c.label: thread_cpu(c.pid) for c in containers}
        machine1 = machine_snapshot()
        live = json.loads(bench.ros.query(get_stats).message)["current"]
        time.sleep(args.drain)
        final_reply = bench.ros.call(stop, timeout=120.0)
        final = json.loads(final_reply.message) if final_reply.message.startswith("{") else {}
        rss = {c.label: peak_rss_mb(c.pid) for c in containers}
        if not alive():
            raise RuntimeError("a container died during the measurement")
    finally:
        for client in clients:
            bench.ros.destroy(client)
        for container in reversed(containers):
            container.stop()
    logs = {c.label: c.log_text() for c in containers}
    result["source_skips_logged"] = sum(source_skips(text) for text in logs.values())
    bag = Path(f"{uri}_1")
    result["bag_files"] = len(list(bag.glob("*.mcap")) + list(bag.glob("*.db3")))
    try:
        read = read_bag(bag, scenario, topics)
    finally:
        if not args.keep_bags:
            shutil.rmtree(bag, ignore_errors=True)
            shutil.rmtree(uri, ignore_errors=True)
            bench.last_free = time.monotonic()
    counts = window_counts(read["records"], topics, t0, t1)
    window_s = (t1 - t0) / 1e9
    cpu = {label: sum(cpu1[label]) - sum(cpu0[label]) for label in cpu0}
    result["cpu_sys_s"] = {label: cpu1[label][1] - cpu0[label][1] for label in cpu0}
    result["background_cpu_s"], result["kernel_cpu_s"] = other_cpu(
        machine0, machine1, sum(cpu.values()), {c.pid for c in containers} | {os.getpid()})
    result["peak_dirty_mb"], result["dirty_threshold_mb"] = peak_dirty, dirty_pages_mb()[1]
    result["thread_cpu_s"] = {label: thread_groups(threads0[label], threads1[label],
                                                   writer_tids if label == recorder_proc.label else set())
                              for label in threads0}
    result["writer_thread_cpu_s"] = (result["thread_cpu_s"][recorder_proc.label].get("bag writer")
                                     if len(writer_tids) == 1 else None)
    recorded_bytes = sum(c["bytes"] for c in counts.values())
    bag_total = sum(len(v) for v in read["records"].values())
    recorder_written = sum(t.get("written", 0) for t in final.get("topics", {}).values())
    result.update({
        "window_s": window_s, "topics": counts,
        "published": sum(c["published"] for c in counts.values()),
        "recorded": sum(c["recorded"] for c in counts.values()),
        "lost": sum(c["lost"] for c in counts.values()),
        "duplicates": sum(c["duplicates"] for c in counts.values()),
        "min_pub_ratio": min(c["pub_ratio"] for c in counts.values()),
        "recorded_bytes": recorded_bytes, "mb_per_s": recorded_bytes / MB / window_s,
        "cpu_s": cpu, "total_cpu_s": sum(cpu.values()),
        "recorder_cpu_s": cpu["recorder"] if mode == "dds" else None,
        "peak_rss_mb": rss, "recorder_rss_mb": rss[recorder_proc.label],
        "latency_ms": live.get("write_latency_ms"),
        "recorder_counters": final.get("topics"), "recorder_error": final.get("error"),
        "bag_messages": bag_total, "bag_metadata_messages": read["metadata_count"],
        "bag_matches_recorder_written": bag_total == recorder_written,
    })
    result["lost_pct"] = 100.0 * result["lost"] / result["published"] if result["published"] else 0.0
    result["total_cpu_s_per_gb"] = (result["total_cpu_s"] / (recorded_bytes / GB)) if recorded_bytes else None
    result["lossless"] = (result["lost"] == 0 and result["min_pub_ratio"] >= PUBLISH_RATE_OK
                          and not result["recorder_error"])
    return result


def run_drivers_only(bench: Bench, scenario: Scenario) -> dict[str, Any]:
    """The drivers alone: CPU and RSS over a window of the same length."""
    from composition_interfaces.srv import ListNodes
    args = bench.args
    tag = bench.next_tag(scenario, "drivers")
    container = Container("drivers", f"bench_{tag}", [bench.write_yaml(f"{tag}_drivers", scenario.components())],
                          bench.workdir / f"{tag}.log", args.executor, args.threads, bench.workdir)
    client = bench.ros.node.create_client(ListNodes, f"/bench_{tag}/_container/list_nodes")
    try:
        deadline = time.monotonic() + args.startup_timeout
        bench.ros.wait_for(client, deadline, container.alive)
        names = bench.ros.call(client).full_node_names
        if len(names) != len(scenario.components()):
            raise RuntimeError(f"only {len(names)} of {len(scenario.components())} drivers loaded")
        time.sleep(args.settle + 1.0)
        t0 = time.time_ns()
        cpu0 = cpu_times(container.pid)
        threads0 = thread_cpu(container.pid)
        machine0 = machine_snapshot()
        time.sleep(scenario.seconds)
        t1 = time.time_ns()
        cpu1 = cpu_times(container.pid)
        threads1 = thread_cpu(container.pid)
        machine1 = machine_snapshot()
        rss = peak_rss_mb(container.pid)
        if not container.alive():
            raise RuntimeError("the drivers container died during the measurement")
    finally:
        bench.ros.node.destroy_client(client)
        container.stop()
    cpu = sum(cpu1) - sum(cpu0)
    user_other, kernel_other = other_cpu(machine0, machine1, cpu, {container.pid, os.getpid()})
    return {"mode": "drivers", "scenario": scenario.key, "window_s": (t1 - t0) / 1e9, "total_cpu_s": cpu,
            "cpu_s": {"drivers": cpu}, "cpu_sys_s": {"drivers": cpu1[1] - cpu0[1]}, "peak_rss_mb": {"drivers": rss},
            "background_cpu_s": user_other, "kernel_cpu_s": kernel_other,
            "thread_cpu_s": {"drivers": thread_groups(threads0, threads1, set())},
            "source_skips_logged": source_skips(container.log_text())}


def run_baseline(bench: Bench, scenario: Scenario) -> dict[str, Any]:
    """S3 ipc once more, with the code of ``--baseline`` (checked out into a temporary worktree) and the single
    executor: the reference the issue-12 target compares the current code's CPU per message with."""
    repo = Path(__file__).resolve().parent.parent
    checkout = bench.workdir / "baseline_code"
    subprocess.run(["git", "worktree", "add", "--detach", "--force", str(checkout), bench.args.baseline],
                   cwd=repo, check=True, capture_output=True, timeout=120)
    bench.code, bench.executor = checkout, "single"
    try:
        result = run_recorder_mode(bench, scenario, "ipc")
    finally:
        bench.code, bench.executor = None, None
        subprocess.run(["git", "worktree", "remove", "--force", str(checkout)], cwd=repo, capture_output=True,
                       timeout=120)
    result["mode"] = "baseline"
    result["code"] = bench.args.baseline
    return result


def run_ceiling(bench: Bench, scenario: Scenario) -> dict[str, Any]:
    """Write the scenario's nominal bytes, message by message in due order, as fast as Python can."""
    topics = scenario.topics()
    events: list[tuple[float, int]] = []
    for spec in topics.values():
        count = round(spec.rate * scenario.seconds)
        events += [(k / spec.rate, spec.size) for k in range(count)]
    events.sort()
    tag = bench.next_tag(scenario, "ceiling")
    spec_path = bench.workdir / f"{tag}.json"
    data_path = bench.workdir / f"{tag}.bin"
    spec_path.write_text(json.dumps({"path": str(data_path), "sizes": [size for _, size in events]}))
    def write_once() -> dict[str, Any]:
        machine0 = machine_snapshot()
        done = subprocess.run([sys.executable, "-c", CEILING_WORKER, str(spec_path)], capture_output=True,
                              text=True, timeout=600)
        machine1 = machine_snapshot()
        data_path.unlink(missing_ok=True)
        if done.returncode != 0:
            raise RuntimeError(f"ceiling writer failed: {done.stderr.strip()}")
        out = json.loads(done.stdout)
        # other processes, and the kernel (its writeback of this file included), during the writer's life
        out["background_cpu_s"], out["kernel_cpu_s"] = other_cpu(machine0, machine1, out["cpu_s"], {os.getpid()})
        return out

    # On this kind of VM the kernel's cost of a buffered write depends several-fold on the page-cache pages
    # it gets: pages a big unlink freed moments ago are reused at ~0.2 CPU s/GB (GB/s), while after a few
    # seconds the guest has handed them back to the host and fresh pages cost ~1.5-2 CPU s/GB (~500 MB/s).
    # A recorder writing continuously lives in the second regime, so each ceiling run waits
    # --page-pause seconds after the last deletion first; the median of those runs is the ceiling. One more run straight after
    # (reusing the pages just freed) is reported as the warm, burst figure.
    # --page-pause: see wait_for_fresh_pages.
    runs = []
    try:
        for _ in range(max(1, bench.args.ceiling_repeats)):
            wait_for_fresh_pages(bench)
            runs.append(write_once())
            bench.last_free = time.monotonic()
        warm = write_once()
    finally:
        data_path.unlink(missing_ok=True)
        spec_path.unlink(missing_ok=True)
        bench.last_free = time.monotonic()
    out = sorted(runs, key=lambda r: r["seconds"])[len(runs) // 2]
    return {"mode": "ceiling", "scenario": scenario.key, "recorded_bytes": out["bytes"], "messages": len(events),
            "write_s": out["seconds"], "window_s": out["seconds"] + out["fsync_s"],
            "mb_per_s": out["bytes"] / MB / out["seconds"],
            "mb_per_s_with_fsync": out["bytes"] / MB / (out["seconds"] + out["fsync_s"]),
            "total_cpu_s": out["cpu_s"], "total_cpu_s_per_gb": out["cpu_s"] / (out["bytes"] / GB),
            "background_cpu_s": out["background_cpu_s"], "kernel_cpu_s": out["kernel_cpu_s"],
            "all_runs_mb_per_s": [r["bytes"] / MB / r["seconds"] for r in runs],
            "all_runs_cpu_s_per_gb": [r["cpu_s"] / (r["bytes"] / GB) for r in runs],
            "warm_mb_per_s": warm["bytes"] / MB / warm["seconds"],
            "warm_cpu_s_per_gb": warm["cpu_s"] / (warm["bytes"] / GB)}


def direct_write_once(path: Path, total: int) -> dict[str, Any]:
    """Write ``total`` bytes (whole 8 MiB blocks) to a new file with O_DIRECT, fsync; seconds and CPU."""
    from baglib.write.direct_file import DirectFile, open_exclusive
    out = open_exclusive(path, buffering=0)
    if not isinstance(out, DirectFile):  # open_exclusive falls back to a buffered file without O_DIRECT
        out.close()
        raise RuntimeError(f"the filesystem of {path.parent} does not support O_DIRECT")
    block = mmap.mmap(-1, DIRECT_BLOCK)  # anonymous mappings are page-aligned, as O_DIRECT needs
    block.write(os.urandom(DIRECT_BLOCK))
    view = memoryview(block)
    try:
        cpu0, t0 = time.process_time(), time.perf_counter()
        for _ in range(total // DIRECT_BLOCK):
            done = 0
            while done < DIRECT_BLOCK:
                done += os.write(out.fileno(), view[done:])
        t1 = time.perf_counter()
        out.close(sync=True)
        t2, cpu1 = time.perf_counter(), time.process_time()
    finally:
        out.close()
        view.release()
        block.close()
    return {"bytes": total // DIRECT_BLOCK * DIRECT_BLOCK, "write_s": t1 - t0, "fsync_s": t2 - t1,
            "cpu_s": cpu1 - cpu0}


def run_direct_write(bench: Bench) -> dict[str, Any]:
    """The direct-write limit of the bags' filesystem: median of --ceiling-repeats runs (module docstring)."""
    path = bench.workdir / "direct_write.bin"
    total = int(bench.args.direct_mb * 2**20)
    runs = []
    try:
        for _ in range(max(1, bench.args.ceiling_repeats)):
            wait_for_fresh_pages(bench)
            machine0 = machine_snapshot()
            run = direct_write_once(path, total)
            machine1 = machine_snapshot()
            path.unlink()
            bench.last_free = time.monotonic()
            run["background_cpu_s"], run["kernel_cpu_s"] = other_cpu(machine0, machine1, run["cpu_s"], {os.getpid()})
            run["mb_per_s"] = run["bytes"] / MB / (run["write_s"] + run["fsync_s"])
            runs.append(run)
    finally:
        path.unlink(missing_ok=True)
    median = sorted(runs, key=lambda r: r["mb_per_s"])[len(runs) // 2]
    return {"mode": "direct", "path": str(path.parent), "block_bytes": DIRECT_BLOCK, **median,
            "window_s": median["write_s"] + median["fsync_s"],
            "cpu_s_per_gb": median["cpu_s"] / (median["bytes"] / GB),
            "all_runs_mb_per_s": [r["mb_per_s"] for r in runs]}


# ----------------------------------------------------------------------------------------------- reporting
def fmt(value: Any, spec: str = ".1f", missing: str = "-") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return missing
    return format(value, spec)


def table(headers: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(headers)]
    line = lambda cells: "  ".join(c.ljust(w) if i < 2 else c.rjust(w)  # noqa: E731
                                   for i, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([line(headers), line(["-" * w for w in widths]), *(line(r) for r in rows)])


def apply_recorder_cpu(results: dict[str, Any]) -> None:
    """ipc recorder CPU = ipc total - drivers-only total (same scenario)."""
    ipc, drivers = results.get("ipc"), results.get("drivers")
    if ipc and "error" not in ipc and drivers and "error" not in drivers:
        scale = ipc["window_s"] / drivers["window_s"]
        ipc["recorder_cpu_s"] = ipc["total_cpu_s"] - drivers["total_cpu_s"] * scale
        ipc["recorder_cpu_note"] = "ipc total minus drivers-only total"
        writer = ipc.get("writer_thread_cpu_s")
        # The subtraction assumes the drivers cost the same with and without the recorder next to them; the
        # rclpy executor's per-wake overhead shrinks when it is busier, so it can come out below the bag
        # writer thread's own CPU (which the recorder certainly spent): then the writer thread is the estimate.
        ipc["recorder_cpu_subtraction_below_writer"] = writer is not None and ipc["recorder_cpu_s"] < writer
        ipc["recorder_cpu_best_s"] = max(ipc["recorder_cpu_s"], writer or 0.0)
    dds = results.get("dds")
    if dds and "error" not in dds and dds.get("recorder_cpu_s") is not None:
        dds["recorder_cpu_best_s"] = dds["recorder_cpu_s"]
    for mode in ("ipc", "dds"):
        entry = results.get(mode)
        if entry and "error" not in entry and entry.get("recorder_cpu_s") is not None:
            if entry["recorded_bytes"]:
                entry["recorder_cpu_s_per_gb"] = entry["recorder_cpu_s"] / (entry["recorded_bytes"] / GB)
            if entry["recorded"]:
                entry["recorder_cpu_us_per_msg"] = 1e6 * entry["recorder_cpu_s"] / entry["recorded"]
                entry["recorder_cpu_best_us_per_msg"] = 1e6 * entry["recorder_cpu_best_s"] / entry["recorded"]
                if entry.get("writer_thread_cpu_s") is not None:
                    entry["writer_thread_us_per_msg"] = 1e6 * entry["writer_thread_cpu_s"] / entry["recorded"]


def topic_table(results: dict[str, Any]) -> str:
    rows = []
    for mode in RECORDER_MODES:
        entry = results.get(mode)
        if not entry or "error" in entry:
            continue
        for name, c in entry["topics"].items():
            rows.append([mode, name, f"{c['published']}{'~' if c['estimated'] else ''}", str(c["recorded"]),
                         str(c["lost"]), fmt(100.0 * c["lost"] / c["published"] if c["published"] else 0.0, ".2f"),
                         fmt(100.0 * c["pub_ratio"], ".1f"), fmt(c["bytes"] / MB / entry["window_s"], ".1f")])
    return table(["mode", "topic", "published", "recorded", "lost", "lost %", "pub %nom", "MB/s"], rows)


def mode_table(results: dict[str, Any]) -> str:
    rows = []
    for mode in (*RECORDER_MODES, "drivers", "ceiling", "baseline"):
        e = results.get(mode)
        if not e:
            continue
        if "error" in e:
            rows.append([mode, "ERROR: " + e["error"][:60]] + [""] * 15)
            continue
        lat = e.get("latency_ms") or {}
        rss = e.get("peak_rss_mb") or {}
        rss_text = "/".join(f"{v:.0f}" for v in rss.values()) if rss else "-"
        rows.append([
            mode, str(e.get("published", "-")), str(e.get("recorded", "-")),
            fmt(e.get("lost_pct"), ".2f"), fmt(e.get("mb_per_s"), ".1f"), fmt(e.get("direct_write_pct"), ".0f"),
            fmt(e.get("recorder_cpu_s"), ".2f"), fmt(e.get("writer_thread_cpu_s"), ".2f"),
            fmt(e.get("total_cpu_s"), ".2f"),
            fmt(sum(e["cpu_sys_s"].values()) if "cpu_sys_s" in e else e.get("cpu_sys_s"), ".2f"),
            fmt(e.get("recorder_cpu_s_per_gb"), ".2f"), fmt(e.get("total_cpu_s_per_gb"), ".2f"), rss_text,
            fmt(lat.get("p50"), ".1f"), fmt(lat.get("p99"), ".1f"), fmt(e.get("kernel_cpu_s"), ".1f"),
            fmt(e.get("background_cpu_s"), ".1f")])
    return table(["mode", "published", "recorded", "lost %", "MB/s", "% direct", "rec CPU s", "writer s",
                  "tot CPU s", "sys s", "rec s/GB", "tot s/GB", "peak RSS MB", "lat p50 ms", "p99 ms",
                  "kernel s", "other s"], rows)


def notes(results: dict[str, Any]) -> list[str]:
    out = []
    for mode in RECORDER_MODES:
        e = results.get(mode)
        if not e or "error" in e:
            continue
        if e["min_pub_ratio"] < PUBLISH_RATE_OK:
            out.append(f"{mode}: drivers published only {100 * e['min_pub_ratio']:.1f} % of nominal on the worst "
                       f"topic (source skips logged: {e['source_skips_logged']})")
        if e["duplicates"]:
            out.append(f"{mode}: {e['duplicates']} duplicate messages in the bag")
        if not e["bag_matches_recorder_written"]:
            out.append(f"{mode}: bag holds {e['bag_messages']} messages but the recorder counted "
                       f"{sum(t.get('written', 0) for t in (e['recorder_counters'] or {}).values())} written")
        if e["recorder_error"]:
            out.append(f"{mode}: recorder error: {e['recorder_error']}")
        if e.get("dirty_threshold_mb") and e["peak_dirty_mb"] > 0.8 * e["dirty_threshold_mb"]:
            out.append(f"{mode}: the page cache held up to {e['peak_dirty_mb']:.0f} MB of unwritten data, near the "
                       f"kernel's dirty limit ({e['dirty_threshold_mb']:.0f} MB): writes get throttled to the "
                       "disk's writeback speed there")
    if results.get("ipc", {}).get("recorder_cpu_note"):
        out.append("ipc rec CPU = ipc total - drivers-only total (drivers and recorder share one process); "
                   "writer s = CPU of the recorder's bag-writer thread alone (intake runs on the executor thread)")
        if results["ipc"].get("recorder_cpu_subtraction_below_writer"):
            out.append("ipc: the subtraction came out below the writer thread's own CPU, so it is unreliable "
                       "(the executor's per-wake overhead is not additive); targets use the writer thread CPU")
    for mode in ("ipc", "dds", "drivers", "ceiling"):
        e = results.get(mode)
        if e and "error" not in e and (e.get("background_cpu_s") or 0) > 0.1 * e.get("window_s", 10) * (os.cpu_count() or 1):
            out.append(f"{mode}: other processes used {e['background_cpu_s']:.1f} CPU s during the window "
                       "(a busy machine: numbers are perturbed)")
        if e and e.get("attempts", 1) > 1:
            out.append(f"{mode}: run {e['attempts']} times because other processes perturbed it; the least "
                       "perturbed run is shown")
    if results.get("ceiling"):
        c = results["ceiling"]
        out.append(f"ceiling: {c['recorded_bytes'] / MB:.0f} MB in {c['messages']} writes, {c['write_s']:.2f} s "
                   f"({c['mb_per_s_with_fsync']:.0f} MB/s including a final fsync); median of "
                   + ", ".join(f"{v:.0f}" for v in c["all_runs_mb_per_s"]) + " MB/s at "
                   + ", ".join(f"{v:.2f}" for v in c["all_runs_cpu_s_per_gb"])
                   + f" CPU s/GB; warm (right after an unlink, reusing its pages): {c['warm_mb_per_s']:.0f} MB/s at "
                   f"{c['warm_cpu_s_per_gb']:.2f} CPU s/GB")
    return out


def apply_direct_share(report: dict[str, Any]) -> None:
    """Every ipc row's MB/s (and each buffered ceiling's) as a percentage of the direct-write limit."""
    direct = report.get("direct_write")
    if not direct or "error" in direct:
        return
    entries: list[Optional[dict[str, Any]]] = []
    for key in ("S1", "S3"):
        block = report.get(key) or {}
        entries += [block.get(mode) for mode in (*IPC_MODES, "ceiling")]
        for run in (block.get("repeat") or {}).get("results", []):
            entries += [run.get(mode) for mode in IPC_MODES]
    s2 = report.get("S2") or {}
    entries += [step for step in s2.get("steps", []) if step.get("mode") in IPC_MODES]
    entries.append(s2.get("ceiling"))
    for entry in entries:
        if entry and "error" not in entry and entry.get("mb_per_s"):
            entry["direct_write_pct"] = 100.0 * entry["mb_per_s"] / direct["mb_per_s"]


def cpu_per_gb_ratio(ipc: Optional[dict[str, Any]], dds: Optional[dict[str, Any]]) -> Optional[float]:
    """ipc total CPU s/GB over dds total CPU s/GB, None when either is missing or failed."""
    if not ipc or not dds or "error" in ipc or "error" in dds:
        return None
    a, b = ipc.get("total_cpu_s_per_gb"), dds.get("total_cpu_s_per_gb")
    return a / b if a and b else None


def p99_ratio(split: Optional[dict[str, Any]], ipc: Optional[dict[str, Any]]) -> Optional[float]:
    """split over unsplit receive-to-write latency p99, None when either is missing or failed."""
    a, b = ((e.get("latency_ms") or {}).get("p99") if e and "error" not in e else None for e in (split, ipc))
    return a / b if a and b else None


def repeat_summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The loss distribution of --repeat runs of S1 per recorder mode, the ipc / dds CPU ratio and the
    split / ipc latency p99 ratio per run."""
    per_mode: dict[str, Any] = {}
    for mode in RECORDER_MODES:
        entries = [run[mode] for run in runs if mode in run]
        if not entries:
            continue
        pcts = [e["lost_pct"] for e in entries if "error" not in e]
        per_mode[mode] = {"runs": len(entries), "failed_runs": len(entries) - len(pcts),
                          "lossless_runs": sum(1 for e in entries if "error" not in e and e["lossless"]),
                          "lost_pct_min": min(pcts, default=None), "lost_pct_max": max(pcts, default=None),
                          "lost_pct_median": statistics.median(pcts) if pcts else None}
    both = "ipc" in per_mode and "dds" in per_mode
    split = "ipc" in per_mode and "split" in per_mode
    return {"per_mode": per_mode,
            "ipc_dds_cpu_per_gb_ratio": [cpu_per_gb_ratio(r.get("ipc"), r.get("dds")) for r in runs] if both else None,
            "split_ipc_p99_ratio": [p99_ratio(r.get("split"), r.get("ipc")) for r in runs] if split else None}


def print_repeat(repeat: dict[str, Any]) -> None:
    runs = repeat["results"]
    print(f"\n== S1 repeated: {len(runs)} runs back to back (run 1 is the one shown in full above)")
    rows = []
    for number, run in enumerate(runs, 1):
        for mode, e in run.items():
            if "error" in e:
                rows.append([str(number), mode, "ERROR " + e["error"][:50]] + [""] * 8)
                continue
            rows.append([str(number), mode, str(e["published"]), str(e["lost"]), fmt(e["lost_pct"], ".2f"),
                         fmt(e["mb_per_s"], ".1f"), fmt(e.get("direct_write_pct"), ".0f"),
                         fmt(e.get("total_cpu_s_per_gb"), ".2f"), fmt((e.get("latency_ms") or {}).get("p99"), ".1f"),
                         fmt(e.get("kernel_cpu_s"), ".1f"), verdict(e)])
    print(table(["run", "mode", "published", "lost", "lost %", "MB/s", "% direct", "tot s/GB", "p99 ms", "kernel s",
                 "lossless"], rows))
    for mode, m in repeat["per_mode"].items():
        print(f"  {mode}: lossless in {m['lossless_runs']} of {m['runs']} runs"
              + (f" ({m['failed_runs']} failed)" if m["failed_runs"] else "")
              + f"; lost % min {fmt(m['lost_pct_min'], '.2f')} / median {fmt(m['lost_pct_median'], '.2f')} / "
              f"max {fmt(m['lost_pct_max'], '.2f')}")
    if repeat["ipc_dds_cpu_per_gb_ratio"] is not None:
        print("  ipc / dds total CPU s/GB per run: "
              + ", ".join(fmt(r, ".2f") for r in repeat["ipc_dds_cpu_per_gb_ratio"]))
    if repeat["split_ipc_p99_ratio"] is not None:
        print("  split / ipc receive-to-write p99 per run: "
              + ", ".join(fmt(r, ".2f") for r in repeat["split_ipc_p99_ratio"]))


def print_direct(report: dict[str, Any]) -> None:
    d = report["direct_write"]
    if "error" in d:
        print(f"\n== Direct-write limit: ERROR {d['error']}")
        return
    ceiling = (report.get("S1") or {}).get("ceiling") or {}
    print(f"\n== Direct-write limit of {d['path']}: {d['mb_per_s']:.0f} MB/s (O_DIRECT, {d['bytes'] / 2**20:.0f} MiB "
          f"in {d['block_bytes'] // 2**20} MiB blocks + fsync, {d['cpu_s_per_gb']:.2f} CPU s/GB; median of "
          + ", ".join(f"{v:.0f}" for v in d["all_runs_mb_per_s"]) + " MB/s)"
          + (f"; buffered ceiling (S1) {ceiling['mb_per_s']:.0f} MB/s = {ceiling['direct_write_pct']:.0f} % of it"
             if "direct_write_pct" in ceiling else ""))


def print_s1(s1: dict[str, Any], scenario: Scenario, args: argparse.Namespace) -> None:
    print(f"\n== {scenario.title}: {scenario.describe()}; {args.storage}, cache {args.cache_mb:g} MiB, "
          f"executor {args.executor}")
    print(topic_table(s1))
    print()
    print(mode_table(s1))
    for line in notes(s1):
        print("  * " + line)


def verdict(step: dict[str, Any]) -> str:
    if step["lossless"]:
        return "yes"
    reasons = []
    if step["lost"]:
        reasons.append("lost")
    if step["min_pub_ratio"] < PUBLISH_RATE_OK:
        reasons.append("drivers slow")
    if step["recorder_error"]:
        reasons.append("error")
    return "NO (" + ", ".join(reasons) + ")"


def print_s2(s2: dict[str, Any]) -> None:
    print(f"\n== S2 ramp: +1 camera per step, {s2['base']}, cap {s2['cap']}, {s2['seconds']:g} s windows")
    rows = []
    for step in s2["steps"]:
        if "error" in step:
            rows.append([step["mode"], str(step["cameras"]), "ERROR " + step["error"][:50]] + [""] * 8)
            continue
        rows.append([step["mode"], str(step["cameras"]), str(step["lost"]), fmt(step["lost_pct"], ".2f"),
                     fmt(100 * step["min_pub_ratio"], ".1f"), fmt(step["mb_per_s"], ".1f"),
                     fmt(step.get("direct_write_pct"), ".0f"), fmt(step["total_cpu_s"], ".2f"),
                     fmt(step.get("kernel_cpu_s"), ".1f"),
                     fmt(step.get("background_cpu_s"), ".1f"), verdict(step)])
    print(table(["mode", "cameras", "lost", "lost %", "min pub %nom", "MB/s", "% direct", "tot CPU s", "kernel s",
                 "other s",
                 "lossless"],
                rows))
    for mode, best in s2["largest_lossless"].items():
        print(f"  largest lossless camera count, {mode}: {best}"
              + ("" if s2["limit_reached"].get(mode) else f" (no loss up to the cap of {s2['cap']})"))
    if s2.get("ceiling"):
        c = s2["ceiling"]
        print(f"  ceiling for the ipc overload step ({c['cameras']} cameras): {c['mb_per_s']:.0f} MB/s (median of "
              + ", ".join(f"{v:.0f}" for v in c["all_runs_mb_per_s"])
              + f"; warm, reusing just-freed pages: {c['warm_mb_per_s']:.0f} MB/s)")


def print_s3(s3: dict[str, Any], scenario: Scenario) -> None:
    print(f"\n== {scenario.title}: {scenario.describe()}")
    print(mode_table(s3))
    for mode in ("ipc", "dds"):
        e = s3.get(mode)
        if e and "error" not in e:
            print(f"  {mode}: recorder CPU per recorded message: {fmt(e.get('recorder_cpu_us_per_msg'), '.1f')} us"
                  + (f" (ipc total - drivers only); writer thread alone {fmt(e.get('writer_thread_us_per_msg'), '.1f')} us"
                     if mode == "ipc" else f"; writer thread {fmt(e.get('writer_thread_us_per_msg'), '.1f')} us")
                  + f" ({e['recorded']} messages, lost {e['lost']})")
    baseline, ipc = s3.get("baseline"), s3.get("ipc")
    if good(baseline) and good(ipc):
        print(f"  total CPU per recorded message: ipc {total_us_per_msg(ipc):.1f} us, the code at "
              f"{baseline['code']} (single executor) {total_us_per_msg(baseline):.1f} us "
              f"({baseline['recorded']} messages, drivers at >= {100 * baseline['min_pub_ratio']:.0f} % of "
              f"nominal): {total_us_per_msg(baseline) / total_us_per_msg(ipc):.2f}x lower")
    for line in notes(s3):
        print("  * " + line)


def good(entry: Optional[dict[str, Any]]) -> bool:
    """A mode that ran and produced results."""
    return entry is not None and "error" not in entry


def total_us_per_msg(entry: dict[str, Any]) -> float:
    """Drivers and recorder: the container's whole CPU in the window per recorded message."""
    return 1e6 * entry["total_cpu_s"] / max(1, entry["recorded"])


def add_s2_disk_targets(s2: Optional[dict[str, Any]], add: Callable[[str, Optional[bool], str], None]) -> None:
    """Issue 12's S2 targets: ipc lossless with S2_TARGET_CAMERAS cameras, and lossless at >= S2_TARGET_DIRECT_PCT
    of the direct-write limit. Both are judged on the largest lossless ipc step; below the target they fail only
    when ipc did lose messages at the next step (a ramp capped below the target proves nothing)."""
    steps = [step for step in (s2 or {}).get("steps", []) if step["mode"] == "ipc" and "error" not in step]
    cameras_name = f"S2 ipc lossless with {S2_TARGET_CAMERAS} cameras"
    direct_name = f"S2 ipc lossless at >= {S2_TARGET_DIRECT_PCT} % of the direct-write limit"
    if not s2 or not steps:
        add(cameras_name, None, "not measured")
        add(direct_name, None, "not measured")
        return
    best = max((step for step in steps if step["lossless"]), key=lambda step: step["cameras"], default=None)
    count = best["cameras"] if best else 0
    reached = s2["limit_reached"].get("ipc", False)
    capped = "" if reached else f" (no loss up to the cap of {s2['cap']})"
    add(cameras_name, True if count >= S2_TARGET_CAMERAS else (False if reached else None),
        f"largest lossless ipc step: {count} cameras{capped}")
    pct = best.get("direct_write_pct") if best else 0.0
    if pct is None:
        add(direct_name, None, "no direct-write limit measured (--direct-mb 0)")
        return
    add(direct_name, True if pct >= S2_TARGET_DIRECT_PCT else (False if reached else None),
        f"{best['mb_per_s'] if best else 0:.0f} MB/s at {count} cameras = {pct:.0f} % of the direct-write limit"
        f"{capped}")


def evaluate_targets(report: dict[str, Any], args: argparse.Namespace) -> list[dict[str, Any]]:
    targets: list[dict[str, Any]] = []

    def add(name: str, ok: Optional[bool], detail: str) -> None:
        targets.append({"target": name, "result": "N/A" if ok is None else ("PASS" if ok else "FAIL"),
                        "detail": detail})

    s1 = report.get("S1") or {}
    ipc, dds = s1.get("ipc"), s1.get("dds")
    default_cfg = args.storage == "mcap" and args.cache_mb * 1024 * 1024 == DEFAULT_CACHE
    if good(ipc):
        ok = ipc["lost"] == 0 and ipc["min_pub_ratio"] >= PUBLISH_RATE_OK
        add("S1 ipc zero loss (mcap, default cache)", ok if default_cfg else None,
            f"lost {ipc['lost']} of {ipc['published']}, drivers at >= {100 * ipc['min_pub_ratio']:.1f} % of "
            f"nominal" + ("" if default_cfg else " (not the default storage/cache: not evaluated)"))
    else:
        add("S1 ipc zero loss (mcap, default cache)", None, "not measured")
    if good(ipc) and good(dds) and ipc.get("total_cpu_s_per_gb") and dds.get("total_cpu_s_per_gb"):
        a, b = ipc["total_cpu_s_per_gb"], dds["total_cpu_s_per_gb"]
        add("S1 ipc total CPU s/GB <= 1/2 of dds", a <= 0.5 * b, f"ipc {a:.2f} vs dds {b:.2f} s/GB (ratio {a / b:.2f})")
    else:
        add("S1 ipc total CPU s/GB <= 1/2 of dds", None, "not measured")
    split = s1.get("split")
    name = f"S1 split ({args.split_mb:g} MiB files) lossless, write latency p99 <= 2x unsplit"
    if good(ipc) and good(split) and (ipc.get("latency_ms") or {}).get("p99") and (split.get("latency_ms") or {}).get("p99"):
        a, b = split["latency_ms"]["p99"], ipc["latency_ms"]["p99"]
        add(name, split["lost"] == 0 and a <= 2 * b,
            f"lost {split['lost']} of {split['published']}, p99 {a:.1f} vs {b:.1f} ms unsplit (ratio {a / b:.2f}), "
            f"{split.get('bag_files', '?')} files")
    else:
        add(name, None, "not measured")
    s2 = report.get("S2")
    if s2 and "ipc" in s2["largest_lossless"] and "dds" in s2["largest_lossless"]:
        a, b = s2["largest_lossless"]["ipc"], s2["largest_lossless"]["dds"]
        capped = "" if s2["limit_reached"].get("ipc") else f" (ipc capped at {s2['cap']})"
        add("S2 ipc lossless cameras >= 2x dds", a >= max(1, 2 * b),
            f"ipc {a} vs dds {b}{capped}" + (" (no lossless step at all)" if a == 0 else ""))
    else:
        add("S2 ipc lossless cameras >= 2x dds", None, "not measured")
    add_s2_disk_targets(s2, add)
    over = s2.get("ipc_overload") if s2 else None
    if over and s2.get("ceiling"):
        ratio = over["mb_per_s"] / s2["ceiling"]["mb_per_s"]
        add("ipc MB/s >= 70% of ceiling past its lossless limit", ratio >= 0.7,
            f"{over['mb_per_s']:.0f} MB/s at {over['cameras']} cameras vs ceiling {s2['ceiling']['mb_per_s']:.0f} "
            f"MB/s ({100 * ratio:.0f} %)")
    else:
        add("ipc MB/s >= 70% of ceiling past its lossless limit", None,
            "ipc was not driven past its lossless limit" if s2 else "not measured")
    s3 = report.get("S3") or {}
    e3 = s3.get("ipc")
    if good(e3) and e3.get("recorder_cpu_best_us_per_msg") is not None:
        per_msg = e3["recorder_cpu_best_us_per_msg"]
        ok = e3["lost"] == 0 and e3["min_pub_ratio"] >= PUBLISH_RATE_OK and per_msg < 30.0
        how = ("writer thread; the subtraction gave " + fmt(e3["recorder_cpu_us_per_msg"], ".1f") + " us"
               if e3.get("recorder_cpu_subtraction_below_writer") else "ipc total - drivers only")
        add("S3 ipc zero loss and recorder CPU < 30 us/msg", ok,
            f"lost {e3['lost']} of {e3['published']}, drivers at >= {100 * e3['min_pub_ratio']:.1f} % of nominal, "
            f"{per_msg:.1f} us/msg ({how})")
    else:
        add("S3 ipc zero loss and recorder CPU < 30 us/msg", None, "not measured")
    baseline = s3.get("baseline")
    name = "S3 ipc zero loss, drivers + recorder CPU per message <= 1/2 of --baseline"
    if good(e3) and good(baseline):
        ratio = total_us_per_msg(e3) / total_us_per_msg(baseline)
        add(name, e3["lost"] == 0 and e3["min_pub_ratio"] >= PUBLISH_RATE_OK and ratio <= 0.5,
            f"{total_us_per_msg(e3):.1f} vs {total_us_per_msg(baseline):.1f} us/msg at {baseline['code']} "
            f"(ratio {ratio:.2f}); lost {e3['lost']} of {e3['published']}")
    elif args.baseline:
        add(name, None, "not measured")
    repeat = s1.get("repeat")
    if repeat:
        name = "S1 ipc lossless in 5 of 5 consecutive runs"
        m = repeat["per_mode"].get("ipc")
        if m and args.repeat >= 5:
            add(name, m["lossless_runs"] == m["runs"] if default_cfg else None,
                f"lossless in {m['lossless_runs']} of {m['runs']} consecutive runs (all must be); lost % max "
                f"{fmt(m['lost_pct_max'], '.2f')}" + ("" if default_cfg else " (not the default storage/cache)"))
        else:
            add(name, None, "needs ipc and --repeat >= 5")
        name = "S1 ipc total CPU per GB <= 0.33 of dds in every run"
        ratios = repeat["ipc_dds_cpu_per_gb_ratio"]
        if ratios:
            add(name, all(r is not None and r <= 0.33 for r in ratios),
                "ratio per run: " + ", ".join(fmt(r, ".2f") for r in ratios))
        else:
            add(name, None, "needs ipc and dds")
        m, ratios = repeat["per_mode"].get("split"), repeat["split_ipc_p99_ratio"]
        if m and ratios:
            add(f"S1 split lossless, write latency p99 <= 2x unsplit in every run ({m['runs']})",
                m["lossless_runs"] == m["runs"] and all(r is not None and r <= 2 for r in ratios),
                f"split lossless in {m['lossless_runs']} of {m['runs']} runs; p99 ratio per run: "
                + ", ".join(fmt(r, ".2f") for r in ratios))
    if good(ipc):
        limit = args.cache_mb * 1024 * 1024 / 2**20 + 300
        add("S1 ipc container peak RSS < max_cache_size + 300 MB", ipc["recorder_rss_mb"] < limit,
            f"{ipc['recorder_rss_mb']:.0f} MiB vs {limit:.0f} MiB")
    else:
        add("S1 ipc container peak RSS < max_cache_size + 300 MB", None, "not measured")
    return targets


def plot(report: dict[str, Any], path: Path) -> Optional[Path]:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    panels = []
    s1 = report.get("S1") or {}
    modes = [m for m in ("ipc", "dds", "ceiling") if m in s1 and "error" not in s1[m]]
    if modes:
        panels.append(("S1 recorded MB/s", modes, [s1[m]["mb_per_s"] for m in modes]))
        cpu_modes = [m for m in modes if s1[m].get("total_cpu_s_per_gb")]
        panels.append(("S1 total CPU s per recorded GB", cpu_modes, [s1[m]["total_cpu_s_per_gb"] for m in cpu_modes]))
    s3 = report.get("S3") or {}
    s3_modes = [m for m in ("ipc", "dds") if m in s3 and s3[m].get("recorder_cpu_best_us_per_msg") is not None]
    if s3_modes:
        panels.append(("S3 recorder CPU us per message", s3_modes, [s3[m]["recorder_cpu_best_us_per_msg"] for m in s3_modes]))
    s2 = report.get("S2")
    count = len(panels) + (1 if s2 else 0)
    if not count:
        return None
    fig, axes = plt.subplots(1, count, figsize=(4.5 * count, 4))
    axes = [axes] if count == 1 else list(axes)
    for ax, (title, labels, values) in zip(axes, panels):
        ax.bar(labels, values, color=["tab:green", "tab:red", "tab:gray"][:len(labels)])
        ax.set_title(title, fontsize=10)
    if s2:
        ax = axes[-1]
        for mode, color in (("ipc", "tab:green"), ("dds", "tab:red")):
            steps = [s for s in s2["steps"] if s["mode"] == mode and "error" not in s]
            if steps:
                ax.plot([s["cameras"] for s in steps], [s["mb_per_s"] for s in steps], "o-", color=color,
                        label=f"{mode} MB/s")
                lossy = [s for s in steps if not s["lossless"]]
                ax.plot([s["cameras"] for s in lossy], [s["mb_per_s"] for s in lossy], "x", color="black",
                        markersize=10)
        if s2.get("ceiling"):
            ax.axhline(s2["ceiling"]["mb_per_s"], color="tab:gray", linestyle="--", label="ceiling")
        from matplotlib.ticker import MaxNLocator
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel("cameras (x = lossy step)")
        ax.set_title("S2 ramp: recorded MB/s", fontsize=10)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------------------------- main
def git_state() -> dict[str, Any]:
    """The commit measured and the files that differ from it (the container runs the working tree)."""
    repo = Path(__file__).resolve().parent.parent
    def git(*command: str) -> str:
        try:
            return subprocess.run(["git", *command], cwd=repo, capture_output=True, text=True, timeout=10).stdout
        except (OSError, subprocess.SubprocessError):
            return ""
    return {"commit": git("rev-parse", "--short", "HEAD").strip(),
            "modified": [line[3:] for line in git("status", "--porcelain", "--untracked-files=no").splitlines()]}


def parse_arguments(argv: Optional[list[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help="smoke run: S1 only, 3 s window, 3 s page pause, one ceiling and direct-write run, no retries")
    p.add_argument("--scenarios", default="s1,s2,s3", help="comma-separated subset of s1,s2,s3")
    p.add_argument("--modes", default="ipc,split,dds,drivers,ceiling",
                   help="S1/S3 modes to run (S2 always ipc,dds); split = ipc with --split-mb files (S1 only)")
    p.add_argument("--split-mb", type=float, default=256.0, help="storage.max_bagfile_size of the split mode, MiB")
    p.add_argument("--seconds", type=float, default=10.0, help="S1 measured window")
    p.add_argument("--cameras", type=int, default=2, help="S1 cameras")
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--lidar-points", type=int, default=131072)
    p.add_argument("--lidar-rate", type=float, default=10.0)
    p.add_argument("--imu-rate", type=float, default=200.0, help="S1 IMU rate")
    p.add_argument("--s2-seconds", type=float, default=6.0, help="S2 window per step")
    p.add_argument("--s2-max-cameras", type=int, default=8)
    p.add_argument("--s2-base", choices=("rig", "cameras"), default="rig",
                   help="rig: cameras on top of the S1 lidar and IMU; cameras: cameras only")
    p.add_argument("--s3-seconds", type=float, default=10.0)
    p.add_argument("--s3-imus", type=int, default=10)
    p.add_argument("--s3-rate", type=float, default=1000.0)
    p.add_argument("--baseline", metavar="REV",
                   help="S3 also records ipc with the code of this git revision (a temporary worktree) and the "
                        "single executor, for the target 'CPU per message at least 2x lower than it' (issue 12: "
                        "193a15f)")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    p.add_argument("--cache-mb", type=float, default=DEFAULT_CACHE / 2**20, help="storage.max_cache_size in MiB")
    p.add_argument("--executor", choices=("single", "multi", "isolated", "events"), default="single")
    p.add_argument("--threads", type=int, default=2, help="thread_num for --executor multi")
    p.add_argument("--settle", type=float, default=1.0, help="seconds between start_recording and the window")
    p.add_argument("--drain", type=float, default=1.0, help="seconds recorded after the window")
    p.add_argument("--startup-timeout", type=float, default=90.0)
    p.add_argument("--quiet-wait", type=float, default=15.0,
                   help="before each mode, wait up to this long for other processes to go quiet (0: never)")
    p.add_argument("--quiet-cpu", type=float, default=0.3, help="'quiet': other processes use at most this many CPUs")
    p.add_argument("--retries", type=int, default=1,
                   help="repeat a run during which other processes used more than --retry-cpu CPUs on average "
                        "this many times; the least perturbed run is reported")
    p.add_argument("--retry-cpu", type=float, default=0.5)
    p.add_argument("--ceiling-repeats", type=int, default=3,
                   help="ceiling runs per scenario, and direct-write runs; the median counts")
    p.add_argument("--direct-mb", type=float, default=2048.0,
                   help="MiB written with O_DIRECT to measure the direct-write limit of the bags' filesystem "
                        "(0: skip; at least 8)")
    p.add_argument("--repeat", type=int, default=0,
                   help="run S1's recorder modes this many times back to back and report the loss distribution "
                        "(0: once, the plain single-run output)")
    p.add_argument("--page-pause", type=float, default=10.0,
                   help="seconds between deleting a bag (or ceiling file) and the next run, so every run writes "
                        "to fresh page-cache pages as a continuously writing recorder does (see run_ceiling)")
    p.add_argument("--output-dir", default=".", help="where the temporary bag directory is created")
    p.add_argument("--keep-bags", action="store_true", help="do not delete the bags (debugging)")
    p.add_argument("--json", metavar="FILE", help="also write the results as JSON ('-' for stdout)")
    p.add_argument("--plot", metavar="FILE", default="record_bench.png",
                   help="PNG plot (needs matplotlib: the 'plot' extra); '' to skip")
    args = p.parse_args(argv)
    if args.quick:  # a smoke run: S1 only, short windows and pauses (numbers less careful than a full run)
        args.scenarios = "s1"
        args.seconds = min(args.seconds, 3.0)
        args.page_pause = min(args.page_pause, 3.0)
        args.quiet_wait = min(args.quiet_wait, 5.0)
        args.ceiling_repeats = 1
        args.retries = 0
    args.scenario_set = {s.strip().lower() for s in args.scenarios.split(",") if s.strip()}
    args.mode_set = {m.strip().lower() for m in args.modes.split(",") if m.strip()}
    unknown = (args.scenario_set - {"s1", "s2", "s3"}) | (args.mode_set - {*RECORDER_MODES, "drivers", "ceiling"})
    if unknown:
        p.error(f"unknown scenario/mode: {', '.join(sorted(unknown))}")
    if args.repeat < 0:
        p.error("--repeat must be >= 0")
    if 0 < args.direct_mb < DIRECT_BLOCK / 2**20:
        p.error(f"--direct-mb must be 0 (skip) or at least {DIRECT_BLOCK // 2**20}")
    return args


def wait_for_fresh_pages(bench: Bench) -> None:
    """Wait until --page-pause s have passed since the benchmark last deleted a bag or ceiling file.

    Right after a big unlink, this VM's kernel hands the freed page-cache pages to the next writer at a
    fraction of the cost of fresh ones (0.2 instead of ~1.5-2 CPU s/GB); after a few seconds they are gone.
    Without the pause, whichever mode runs after another would get cheaper writes.
    """
    remaining = bench.args.page_pause - (time.monotonic() - bench.last_free)
    if remaining > 0:
        time.sleep(remaining)


def wait_for_quiet(bench: Bench) -> tuple[float, float]:
    """Wait (up to --quiet-wait s) until other processes use less than --quiet-cpu CPUs; (waited s, last load)."""
    started = time.monotonic()
    while True:
        busy0 = machine_busy_seconds()
        time.sleep(1.0)
        load = machine_busy_seconds() - busy0
        waited = time.monotonic() - started
        if load <= bench.args.quiet_cpu or waited >= bench.args.quiet_wait:
            return waited, load


def perturbed(result: dict[str, Any], args: argparse.Namespace) -> bool:
    """Other processes used more than --retry-cpu CPUs on average during the window."""
    window = result.get("window_s") or 0.0
    return window > 0 and (result.get("background_cpu_s") or 0.0) / window > args.retry_cpu


def guarded(bench: Bench, label: str, run: Callable[[], dict[str, Any]], retry: bool = True) -> dict[str, Any]:
    """Run one mode; a run perturbed by other processes is repeated (--retries) and the least perturbed kept."""
    attempts: list[dict[str, Any]] = []
    for attempt in range(1 + (bench.args.retries if retry else 0)):
        wait_for_fresh_pages(bench)
        waited, load = wait_for_quiet(bench) if bench.args.quiet_wait > 0 else (0.0, float("nan"))
        bench.log(f"[{time.strftime('%H:%M:%S')}] {label}{' (repeat: the last run was perturbed)' if attempt else ''}"
                  " ..." + (f" (waited {waited:.0f} s for other processes; machine load now {load:.2f} CPUs)"
                            if waited > 1.5 else ""))
        started = time.monotonic()
        try:
            result = run()
            result["quiet_wait_s"], result["load_before_cpus"] = waited, load
        except Exception as exc:  # noqa: BLE001 - one failed mode is reported, the others still run
            bench.log(f"    FAILED: {type(exc).__name__}: {exc}")
            result = {"error": f"{type(exc).__name__}: {exc}"}
            if attempts:
                break
            return result
        summary = []
        if "lost" in result:
            summary.append(f"lost {result['lost']}/{result['published']}, "
                           f"pub>={100 * result['min_pub_ratio']:.0f}%nom")
        if "mb_per_s" in result:
            summary.append(f"{result['mb_per_s']:.0f} MB/s")
        if "total_cpu_s" in result:
            summary.append(f"cpu {result['total_cpu_s']:.1f} s")
        if "background_cpu_s" in result:
            summary.append(f"other processes {result['background_cpu_s']:.1f} CPU s")
        bench.log(f"    done in {time.monotonic() - started:.0f} s: {', '.join(summary)}")
        attempts.append(result)
        if not perturbed(result, bench.args):
            break
    best = min(attempts, key=lambda r: r.get("background_cpu_s") or 0.0)
    best["attempts"] = len(attempts)
    if len(attempts) > 1:
        best["other_attempts"] = [{k: r.get(k) for k in ("lost", "published", "mb_per_s", "total_cpu_s",
                                                          "background_cpu_s", "lossless")}
                                  for r in attempts if r is not best]
    return best


def run_s1_recorders(bench: Bench, scenario: Scenario, run: int) -> dict[str, Any]:
    """One run of S1's selected recorder modes; ``run`` numbers it in the log under --repeat."""
    label = f" (run {run} of {bench.args.repeat})" if bench.args.repeat else ""
    return {mode: guarded(bench, f"S1 {mode}{label}", lambda: run_recorder_mode(bench, scenario, mode))
            for mode in RECORDER_MODES if mode in bench.args.mode_set}


def run_s1(bench: Bench) -> dict[str, Any]:
    """S1: the recorder modes (--repeat times), then drivers only and the ceiling once."""
    args = bench.args
    scenario = s1_scenario(args)
    runs = [run_s1_recorders(bench, scenario, run) for run in range(1, max(1, args.repeat) + 1)]
    s1: dict[str, Any] = dict(runs[0])
    if "drivers" in args.mode_set:
        s1["drivers"] = guarded(bench, "S1 drivers only", lambda: run_drivers_only(bench, scenario))
    if "ceiling" in args.mode_set:
        s1["ceiling"] = guarded(bench, "S1 ceiling", lambda: run_ceiling(bench, scenario), retry=False)
    for run in runs:  # run 1's entries are s1's own
        apply_recorder_cpu({**run, "drivers": s1.get("drivers")})
    if args.repeat:
        s1["repeat"] = {"results": runs, **repeat_summary(runs)}
    return s1


def main(argv: Optional[list[str]] = None) -> int:
    args = parse_arguments(argv)
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    output_dir = Path(args.output_dir).resolve()
    output_dir.mkdir(parents=True, exist_ok=True)
    workdir = Path(tempfile.mkdtemp(prefix="record_bench_", dir=output_dir))
    log = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    log(f"record_bench: ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}, bags in {workdir}, {os.cpu_count()} CPUs")
    report: dict[str, Any] = {"config": {k: v for k, v in vars(args).items() if not k.endswith("_set")},
                              "environment": {"ros_domain_id": os.environ["ROS_DOMAIN_ID"], "cpus": os.cpu_count(),
                                              "python": sys.version.split()[0], "workdir": str(workdir),
                                              "git": git_state(), "loadavg_start": os.getloadavg()}}
    started = time.monotonic()
    ros = RosClient()
    bench = Bench(args, workdir, ros, log=log)
    try:
        if args.direct_mb > 0:
            report["direct_write"] = guarded(bench, "direct-write limit", lambda: run_direct_write(bench),
                                             retry=False)
        if "s1" in args.scenario_set:
            report["S1"] = run_s1(bench)
        if "s2" in args.scenario_set:
            s2: dict[str, Any] = {"base": "S1 lidar + IMU + cameras" if args.s2_base == "rig" else "cameras only",
                                  "cap": args.s2_max_cameras, "seconds": args.s2_seconds, "steps": [],
                                  "largest_lossless": {}, "limit_reached": {}}
            for mode in ("ipc", "dds"):
                best = 0
                s2["limit_reached"][mode] = False
                for cameras in range(1, args.s2_max_cameras + 1):
                    scenario = s2_scenario(args, cameras)
                    step = guarded(bench, f"S2 {mode} {cameras} camera(s)",
                                   lambda: run_recorder_mode(bench, scenario, mode))
                    step.update({"mode": mode, "cameras": cameras})
                    s2["steps"].append(step)
                    if "error" not in step and step["lossless"]:
                        best = cameras
                        continue
                    s2["limit_reached"][mode] = True
                    if mode == "ipc" and "error" not in step:
                        s2["ipc_overload"] = {"cameras": cameras, "mb_per_s": step["mb_per_s"]}
                        ceiling = guarded(bench, f"S2 ceiling {cameras} camera(s)",
                                          lambda: run_ceiling(bench, scenario), retry=False)
                        if "error" not in ceiling:
                            s2["ceiling"] = {**ceiling, "cameras": cameras}
                    break
                s2["largest_lossless"][mode] = best
            report["S2"] = s2
        if "s3" in args.scenario_set:
            scenario = s3_scenario(args)
            s3: dict[str, Any] = {}
            for mode in ("ipc", "dds"):
                if mode in args.mode_set:
                    s3[mode] = guarded(bench, f"S3 {mode}", lambda: run_recorder_mode(bench, scenario, mode))
            if "drivers" in args.mode_set or "ipc" in args.mode_set:
                s3["drivers"] = guarded(bench, "S3 drivers only", lambda: run_drivers_only(bench, scenario))
            if args.baseline:
                s3["baseline"] = guarded(bench, f"S3 ipc, code at {args.baseline}, executor single",
                                         lambda: run_baseline(bench, scenario))
            apply_recorder_cpu(s3)
            report["S3"] = s3
    finally:
        ros.close()
        if not args.keep_bags:
            shutil.rmtree(workdir, ignore_errors=True)
    report["elapsed_s"] = time.monotonic() - started
    report["environment"]["loadavg_end"] = os.getloadavg()

    apply_direct_share(report)
    report["targets"] = evaluate_targets(report, args)
    # with --json - the JSON alone goes to stdout, the tables to stderr
    with contextlib.redirect_stdout(sys.stderr if args.json == "-" else sys.stdout):
        if "direct_write" in report:
            print_direct(report)
        if "S1" in report:
            print_s1(report["S1"], s1_scenario(args), args)
            if "repeat" in report["S1"]:
                print_repeat(report["S1"]["repeat"])
        if "S2" in report:
            print_s2(report["S2"])
        if "S3" in report:
            print_s3(report["S3"], s3_scenario(args))
        print("\n== Targets")
        for t in report["targets"]:
            print(f"  {t['result']:4}  {t['target']}: {t['detail']}")
        git = report["environment"]["git"]
        print(f"\n(total run time {report['elapsed_s']:.0f} s; code at {git['commit']}"
              + (f" + uncommitted changes in {', '.join(git['modified'])}" if git["modified"] else "")
              + "; 'kernel s' = CPU of kernel threads and interrupts during the window (the writeback of the "
              "bag among them), 'other s' = CPU of other people's processes)", flush=True)
    if args.plot:
        path = plot(report, Path(args.plot))
        log(f"plot written to {path}" if path else "no plot: matplotlib is not installed (pip install '.[plot]')")
    if args.json:
        text = json.dumps(report, indent=2, default=str)
        if args.json == "-":
            print(text)
        else:
            Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
