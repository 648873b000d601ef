"""Stop, start, split and unload, over and over, on a loaded machine: not one accepted message is lost or
miscounted, in either storage (the recorder loaded after each unload alternates between them).

Two busy CPU loops (processes of their own) compete with an in-process container where two IMU drivers publish
at 2 kHz each to a recorder that takes their messages inline, in the drivers' thread. The test cycles through
stop + start, split, and unload + load, each once enough new messages were written, ending bags while intake
callbacks are running; some offers are held back a millisecond after the intake took its session
(:func:`late_offers`), so that a bag's end lands between the two in every run. Every bag is then read back with rosbags: its final counts must report no drop, and every
message counted as received must be in it, in an unbroken sequence for each driver.
"""
from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Iterator

import pytest
from rclpy.node import Node
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from rosbag2_interfaces.srv import SplitBagfile
from std_srvs.srv import Trigger

from component_container.component_manager import ComponentManager
from component_container.startup_file import load_request
from components.recorder.message_cache import MessageCache
from ipc_testing import call, in_process_manager, wait_until

TOPICS = ("/imu_a/imu", "/imu_b/imu")
#: New messages per topic written before the next cycle: ~10 ms at 2 kHz.
PER_CYCLE = 20
#: What each cycle does, in turn: three of four end a bag, where the intake races the end.
CYCLE = ("stop", "split", "unload", "stop")
#: The storage of each recorder loaded, in turn: every unload + load changes it.
STORAGES = ("mcap", "sqlite3")
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
#: The share of offers delayed by a millisecond (:func:`late_offers`).
LATE_OFFERS = 0.05


@pytest.fixture()
def busy_loops(request: pytest.FixtureRequest) -> Iterator[None]:
    """Two processes that keep two CPUs busy; killed by their pids at the end. In the default run they are
    niced: they take every idle moment from the recorder, but not the CPU of the suite's other workers (at
    full priority, beside 4 xdist workers on 2 cores, they starved whole tests for minutes). The sweep's long
    run keeps them at full priority."""
    nice = 0 if request.node.get_closest_marker("sweep") else 19
    loops = [subprocess.Popen([sys.executable, "-c", f"import os; os.nice({nice})\nwhile True: pass"])
             for _ in range(2)]
    try:
        yield
    finally:
        for loop in loops:
            loop.kill()
            loop.wait()


@pytest.fixture()
def late_offers(monkeypatch: pytest.MonkeyPatch) -> None:
    """Some offers reach the cache a millisecond late: the drivers' thread has taken the session and then waits
    (as a preempted thread would), while this thread stops, splits or unloads. The race this widens, a few
    bytecodes wide otherwise, happened in 2 of 110 runs under busy loops; here it happens in every run. Seeded:
    the seed is printed, ``IPC_STRESS_SEED`` replays it."""
    seed = int(os.environ.get("IPC_STRESS_SEED") or random.randrange(2**32))
    print(f"IPC_STRESS_SEED={seed}")
    chance = random.Random(seed)
    push = MessageCache.push

    def late_push(cache: MessageCache, message: Any) -> Any:
        if chance.random() < LATE_OFFERS:
            time.sleep(0.001)
        return push(cache, message)

    monkeypatch.setattr(MessageCache, "push", late_push)


@pytest.fixture()
def manager() -> Iterator[ComponentManager]:
    with in_process_manager("stress_test", use_intra_process_comms=True) as manager:
        yield manager


class Recording:
    """The recorder under test, loaded again after every unload, and the final counts of every bag it closed."""

    def __init__(self, manager: ComponentManager, root: Path) -> None:
        self.manager, self.root = manager, root
        self.client = Node("stress_client", context=manager.context)
        # made once: each new one would wait for the service's discovery again (the name stays across loads)
        self.clients = {name: self.client.create_client(srv_type, f"/stress_recorder/{name}")
                        for name, srv_type in (("start_recording", Trigger), ("split_bagfile", SplitBagfile))}
        self.finished: dict[str, dict[str, Any]] = {}  # bag path -> final counts
        self.loads = 0
        self._load()

    def _load(self) -> None:
        self.loaded = self.manager.load(load_request({
            "package": "components", "plugin": "components::Recorder", "name": "stress_recorder",
            "parameters": {"storage.uri": str(self.root / f"bag{self.loads}"), "storage.storage_id": STORAGES[self.loads % len(STORAGES)],
                           "record.topics": list(TOPICS)}}, 1))
        self.loads += 1
        self.recorder = self.loaded.node

    def written(self) -> dict[str, int]:
        current = self.recorder.stats()["current"] or {"topics": {}}
        return {topic: current["topics"].get(topic, {}).get("written", 0) for topic in TOPICS}

    def wait_for_more(self) -> None:
        before = self.written()
        assert wait_until(lambda: all(n >= before[t] + PER_CYCLE for t, n in self.written().items()), 30.0), \
            self.recorder.stats()["current"]

    def _keep(self, stats: dict[str, Any] | None) -> None:
        assert stats is not None
        self.finished[stats["bag"]] = stats

    def service(self, name: str) -> Any:
        return call(self.client, self.clients[name])

    def cycle(self, n: int) -> None:
        """One of: stop (from this thread, racing the drivers) + start, a split, an unload + a load."""
        self.wait_for_more()
        kind = CYCLE[n % len(CYCLE)]
        if kind == "stop":
            self._keep(self.recorder.stop_recording())
            start = self.service("start_recording")
            assert start.success, start.message
        elif kind == "split":
            self.service("split_bagfile")  # the next file, while the intake goes on
        else:
            assert not self.manager.unload(self.loaded.unique_id).error
            self._keep(self.recorder.stats()["finished"][-1])
            self._load()

    def close(self) -> None:
        self.wait_for_more()
        assert not self.manager.unload(self.loaded.unique_id).error
        self._keep(self.recorder.stats()["finished"][-1])
        self.client.destroy_node()


def sequences(bag: Path) -> dict[str, list[int]]:
    """Per topic, the IMU sequence numbers (orientation_covariance[1]) in the bag, in file order."""
    found: dict[str, list[int]] = defaultdict(list)
    with Reader(bag) as reader:
        for connection, _, raw in reader.messages():
            msg = TYPESTORE.deserialize_cdr(raw, connection.msgtype)
            found[connection.topic].append(int(msg.orientation_covariance[1]))
    return found


@pytest.mark.parametrize("cycles", [50, pytest.param(500, marks=pytest.mark.sweep)])
def test_stop_start_split_unload_under_load_lose_nothing(manager: ComponentManager, busy_loops: None,
                                                       late_offers: None, tmp_path: Path, cycles: int) -> None:
    for topic in TOPICS:
        loaded = manager.load(load_request({"package": "components", "plugin": "components::ImuDriver",
                                            "name": topic.split("/")[1],
                                            "parameters": {"rate": 2000.0, "topic": topic}}, 1))
        assert loaded.node is not None
    recording = Recording(manager, tmp_path)
    for n in range(cycles):
        recording.cycle(n)
    recording.close()
    problems = []
    for bag, stats in recording.finished.items():
        found = sequences(Path(bag))
        for topic in TOPICS:
            counts, seqs = stats["topics"][topic], found.get(topic, [])
            if counts["dropped"] or not counts["received"] == counts["written"] == len(seqs) \
                    or seqs != list(range(seqs[0], seqs[0] + len(seqs))):
                problems.append(f"{Path(bag).name} {topic}: {json.dumps(counts)}, {len(seqs)} in the bag, "
                                f"reasons {stats['drop_reasons'].get(topic)}")
    bags = 1 + sum(1 for n in range(cycles) if CYCLE[n % len(CYCLE)] != "split")  # and the last one
    assert len(recording.finished) == bags and not problems, problems
    assert {stats["current_file"] == "" for stats in recording.finished.values()} == {True}
    assert {Path(bag, "metadata.yaml").read_text().count("storage_identifier: sqlite3") > 0
            for bag in recording.finished} == {True, False}, "both storages"
