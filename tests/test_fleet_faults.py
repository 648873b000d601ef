"""Fleet recording when things go wrong, on containers of this machine (the faults need no second computer):
a container that does not answer at start, a recording whose stop never comes, a container killed mid-session.
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from rosbags.rosbag2 import Reader

from baglib.format import fleet_keys
from ipc_testing import ContainerProcess
from ipc_testing.process import run_command

REPO = Path(__file__).resolve().parents[1]
RIG = [{"package": "components", "plugin": "components::ImuDriver", "name": "imu", "parameters": {"rate": 100.0},
        "extra_arguments": {"use_intra_process_comms": True}}]


def cli(*args: str) -> subprocess.CompletedProcess:
    return run_command([sys.executable, "-m", "ipc_component.cli", *args], 90, cwd=REPO)


@pytest.fixture
def rig(tmp_path: Path):
    """Two containers (/fa/container, /fb/container) with an IMU each, on this test's domain."""
    load = tmp_path / "rig.yaml"
    load.write_text(yaml.safe_dump({"components": RIG}))
    processes = {}
    try:
        for host in ("fa", "fb"):
            (tmp_path / host).mkdir()
            processes[host] = ContainerProcess("--use-intra-process-comms", "--bag-root", str(tmp_path / host),
                                               "--load", str(load), name=f"/{host}/container", cwd=REPO,
                                               log_path=tmp_path / f"{host}.log")
        deadline = time.monotonic() + 60
        while not all(f"/{h}/container\n  1  /imu" in cli("list").stdout for h in processes):
            assert time.monotonic() < deadline, "containers not listed"
        yield processes
    finally:
        for process in processes.values():
            if process.alive():
                os.kill(process.pid, signal.SIGCONT)
            process.kill()


def sequences(bag: Path, topic: str = "") -> list[tuple[int, int]]:
    """(receive time, IMU sequence number) of every message (of ``topic``, else of every IMU topic), read with
    rosbags."""
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        imu = [c for c in reader.connections if (c.topic == topic if topic else c.topic.endswith("/imu/imu"))]
        return [(t, int(typestore.deserialize_cdr(data, c.msgtype).orientation_covariance[1]))
                for c, t, data in reader.messages(connections=imu)]


@pytest.mark.long
def test_a_container_that_does_not_answer_is_named_and_the_others_record(rig, tmp_path: Path) -> None:
    os.kill(rig["fb"].pid, signal.SIGSTOP)  # a hung computer: it answers nothing, not even discovery
    both = ("/fa/container", "/fb/container")
    aborted = cli("record", "start", *both, "--session", "strict", "--in", "1", "--all-or-nothing")
    assert aborted.returncode == 1 and "/fb/container: not found" in aborted.stderr, aborted.stdout + aborted.stderr
    assert "record_strict" not in cli("list", "/fa/container").stdout, "--all-or-nothing left a recorder"

    started = cli("record", "start", *both, "--session", "partial", "--in", "1", "--max-duration", "2")
    assert started.returncode == 2, started.stdout + started.stderr
    assert "Not recording in /fb/container: not found" in started.stderr, started.stderr  # an error: stderr
    assert "/fa/container" in started.stdout and "/fb/container" not in started.stdout, started.stdout
    os.kill(rig["fb"].pid, signal.SIGCONT)
    # --max-duration: no stop is ever sent; the recorder finalizes by itself 2 s after the start.
    metadata = tmp_path / "fa" / "partial" / f"{os.uname().nodename}_fa_container" / "metadata.yaml"
    deadline = time.monotonic() + 30
    while not metadata.exists():
        assert time.monotonic() < deadline, "the recording did not end at its max duration"
        time.sleep(0.1)
    custom = yaml.safe_load(metadata.read_text())["rosbag2_bagfile_information"]["custom_data"]
    start = int(custom[fleet_keys.START_NS]) + int(custom[fleet_keys.CLOCK_OFFSET_NS])
    received = sequences(metadata.parent)
    assert received and all(start <= t < start + 2_000_000_000 for t, _ in received)
    assert received[-1][0] > start + 1_900_000_000, "the window ended early"
    seqs = [s for _, s in received]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    assert not (tmp_path / "fb" / "partial").exists(), "a recorder was loaded into the stopped container"


def test_a_container_named_at_start_is_waited_for_past_the_spin_time(rig, tmp_path: Path) -> None:
    """``record start`` waits for a container named exactly past ``--spin-time`` (up to 5 s more), as ``load``
    waits for its one: a container that hangs for 1.5 s as the command starts (SIGSTOP, then SIGCONT) records
    with the others. Before, it was "not found on the ROS graph" once the spin time was over."""
    os.kill(rig["fb"].pid, signal.SIGSTOP)
    command = subprocess.Popen([sys.executable, "-m", "ipc_component.cli", "record", "start", "/fa/container",
                                "/fb/container", "--session", "late", "--in", "1", "--max-duration", "1",
                                "--spin-time", "0.2"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    try:
        time.sleep(1.5)  # the hang: longer than the command's start and its 0.2 s of discovery
        os.kill(rig["fb"].pid, signal.SIGCONT)
        out, err = command.communicate(timeout=90)
    finally:
        command.kill()
    assert command.returncode == 0, out + err
    assert "/fa/container" in out and "/fb/container" in out, out


@pytest.mark.long
def test_a_killed_container_leaves_a_bag_that_recover_repairs(rig, tmp_path: Path) -> None:
    started = cli("record", "start", "/fa/container", "/fb/container", "--session", "crash", "--in", "0.5",
                  "-p", "storage.flush_interval:=0.5")  # named: other tests' containers share this domain
    assert started.returncode == 0, started.stdout + started.stderr
    time.sleep(3.5)
    killed_ns = time.time_ns()
    rig["fa"].process.send_signal(signal.SIGKILL)
    rig["fa"].process.wait()
    stopped = cli("record", "stop", "--session", "crash")
    assert stopped.returncode == 0 and "/fb/container" in stopped.stdout, stopped.stdout + stopped.stderr

    bag = tmp_path / "fa" / "crash" / f"{os.uname().nodename}_fa_container"
    other = tmp_path / "fb" / "crash" / f"{os.uname().nodename}_fb_container"
    merged = tmp_path / "merged"
    refused = cli("bag", "merge", str(merged), str(bag), str(other))
    assert refused.returncode == 1 and "bag recover" in refused.stderr and not merged.exists(), refused.stderr
    recovered = subprocess.run([sys.executable, "-m", "ipc_component.cli", "bag", "recover", str(bag)], cwd=REPO,
                               capture_output=True, text=True, timeout=60)
    assert recovered.returncode == 0, recovered.stdout + recovered.stderr
    custom = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["custom_data"]
    assert custom[fleet_keys.SESSION] == "crash", "recover dropped the session's custom_data"
    received = sequences(bag)
    seqs = [s for _, s in received]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "a gap in the recovered bag"
    # the loss is bounded by the flush interval (0.5 s) plus the IMU period and scheduling slack
    assert received[-1][0] >= killed_ns - 1_000_000_000, (killed_ns - received[-1][0]) / 1e9

    # merge then takes the recovered bag with the other container's: every message of both, once
    merge = cli("bag", "merge", str(merged), str(bag), str(other), "--align-clocks", "--prefix-container")
    assert merge.returncode == 0, merge.stdout + merge.stderr
    both = sorted(seq for _t, seq in received) + sorted(seq for _t, seq in sequences(other))
    assert sorted(seq for _t, seq in sequences(merged)) == sorted(both)


def test_containers_sharing_a_name_are_refused(tmp_path: Path) -> None:
    """Two containers named alike (every computer's default /ComponentManager) would both take every request."""
    load = tmp_path / "rig.yaml"
    load.write_text(yaml.safe_dump({"components": RIG}))
    twins = [ContainerProcess("--use-intra-process-comms", "--load", str(load), name="/twin/container", cwd=tmp_path,
                              log_path=tmp_path / f"twin{i}.log") for i in range(2)]
    try:
        deadline = time.monotonic() + 60
        while cli("list", "/twin/container").stdout.count("/imu") < 1:
            assert time.monotonic() < deadline, "twins not listed"
        started = cli("record", "start", "/twin/container", "--session", "twins", "--in", "1")
        assert started.returncode == 1, started.stdout + started.stderr
        assert started.stdout == "" and "2 containers have this name" in started.stderr, started.stdout + started.stderr
        assert not list(tmp_path.glob("twins")), "a recorder was loaded"
    finally:
        for process in twins:
            process.kill()


def recorded_messages(session: str) -> dict[str, int]:
    """Messages so far per container of ``session``, from ``record status``."""
    counts = {}
    for line in cli("record", "status", "--session", session).stdout.splitlines()[1:]:
        row = re.search(r"\s(/\S+)\s.*\s[\d.]+ s\s+[\d.]+\s+(\d+)\s+\d+\s", line)  # CONTAINER ... ELAPSED MB/S MESSAGES
        if row:
            counts[row[1]] = int(row[2])
    return counts


def test_two_rigs_on_one_computer_are_merged_apart(rig, tmp_path: Path) -> None:
    """Two containers on this computer (``-r __ns:=/fa``, ``/fb``), each with an IMU driver named ``imu``,
    recorded with ``record start``: ``bag merge`` refuses to interleave their ``/imu/imu`` (``--prefix-host``
    cannot part them: one host), and ``--prefix-container`` keeps each rig's under its container's name."""
    both = ("/fa/container", "/fb/container")
    started = cli("record", "start", *both, "--session", "rigs", "--in", "0.5")
    assert started.returncode == 0, started.stdout + started.stderr
    deadline = time.monotonic() + 60
    while not (counts := recorded_messages("rigs")) or min(counts.get(name, 0) for name in both) < 100:
        assert time.monotonic() < deadline, f"not recording: {counts}"
    stopped = cli("record", "stop", "--session", "rigs")
    assert stopped.returncode == 0, stopped.stdout + stopped.stderr

    host = os.uname().nodename
    bags = [str(tmp_path / name / "rigs" / f"{host}_{name}_container") for name in ("fa", "fb")]
    for option in ((), ("--prefix-host",)):
        refused = cli("bag", "merge", str(tmp_path / "refused"), *bags, *option)
        assert refused.returncode == 1 and not (tmp_path / "refused").exists(), refused.stdout + refused.stderr
        topic = f"/{host.replace('-', '_').replace('.', '_')}/imu/imu" if option else "/imu/imu"
        assert f"{topic} (from {host} /fa/container, {host} /fb/container)" in refused.stderr, refused.stderr
        assert "--prefix-container" in refused.stderr, refused.stderr
        assert "parameter_events" not in refused.stderr  # every node's: one topic, each message names its node

    merged = tmp_path / "merged"
    done = cli("bag", "merge", str(merged), *bags, "--prefix-container")
    assert done.returncode == 0, done.stdout + done.stderr
    with Reader(merged) as reader:
        topics = {c.topic for c in reader.connections}
    assert {"/fa/container/imu/imu", "/fb/container/imu/imu"} <= topics, topics
    assert "/imu/imu" not in topics
    for name, bag in zip(("fa", "fb"), bags):
        own = [seq for t, seq in sequences(Path(bag))]
        apart = [seq for t, seq in sequences(merged, f"/{name}/container/imu/imu")]
        assert apart == own and len(own) >= 100, name
