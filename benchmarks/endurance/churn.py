"""The soak run: one container, and for ``plan.seconds`` a schedule of loads and unloads around the rig.

Start: the container loads, from one start-up file, the rig drivers, the player (paused) and the first recorder,
which thus subscribes to every topic there is at its load; the player is resumed once that recorder has its
topic. Then, on one thread, by the clock (a late step runs at once and the schedule keeps its grid):

* every ``extra_period_s``: a resource sample (resources.Sample), then an extra camera loaded, and unloaded
  ``extra_alive_s`` later;
* every ``handover_period_s``: the next recorder loaded (a bag of its own); once it has written messages of
  every topic of the run, the previous one is stopped (``~/stop_recording``, answered with its final counts once
  its backlog is written: the schedule goes on meanwhile) and then unloaded;
* every tenth of a split: the files the worker has read taken in, the bags of unloaded recorders whose files
  are all read checked and deleted, and once a second the worker stopped or continued by the recorder's
  backlog (reader_pause). A thread of its own (recorders.Collector) hands the recorders' newly finished files
  to the worker.

End: the player paused, its published count read, the player and the rig drivers unloaded, the last recorder
stopped and unloaded, the container stopped with SIGINT (its exit status must be 0), every file read.
"""
from __future__ import annotations

import json
import os
import signal
import time
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import yaml
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rosbag2_interfaces.msg import MessagesLostEvent
from rosbag2_interfaces.srv import Pause, Resume
from std_msgs.msg import String
from std_srvs.srv import Trigger

from baglib.format.cdr_fast import serialize
from baglib.format.metadata import TopicInfo
from baglib.write.writer import BagWriter
from benchmarks.endurance.accounting import Union
from benchmarks.endurance.plan import IPC, PLAYER, REPLAY_TOPIC, Component, SoakPlan
from benchmarks.endurance.reader_pause import ReaderPause
from benchmarks.endurance.recorders import Collector, RecorderRun, check_bag, discard
from benchmarks.endurance.resources import Sample
from benchmarks.record.measure import cpu_seconds, machine_snapshot, other_cpu, peak_rss_mb
from benchmarks.record.modes import RecorderServices
from ipc_testing import ContainerClient, ContainerProcess, call, wait_until

STARTUP_TIMEOUT = 90.0
STOP_TIMEOUT = 120.0  # s the container gets to exit after SIGINT (its own bound: plan.shutdown_timeout_s)
READ_TIMEOUT = 600.0  # s the worker gets, after the end, to read the last files
#: The run stops (failed) when the bags' filesystem has less free space than this: the worker is far behind,
#: and the disk is shared.
MIN_FREE_BYTES = 15 * 10**9


def write_replay_bag(path: Path, messages: int, rate: float) -> None:
    """The player's bag: std_msgs/String "0", "1", ... at ``rate``."""
    with BagWriter(path) as writer:
        writer.add_topic(TopicInfo(REPLAY_TOPIC, "std_msgs/msg/String"))
        for number in range(messages):
            stamp = 1_700_000_000_000_000_000 + round(number * 1e9 / rate)
            writer.write(REPLAY_TOPIC, bytes(serialize(String(data=str(number)))), stamp, stamp)


@dataclass
class Extra:
    index: int
    unique_id: int
    unload_at: float


@dataclass
class ChurnResult:
    """What the run observed; main turns it into the report."""

    samples: list[Sample] = field(default_factory=list)
    recorders: list[RecorderRun] = field(default_factory=list)
    union: Union = field(default_factory=Union)
    problems: list[str] = field(default_factory=list)
    extra_instances: int = 0
    extra_load_failures: list[str] = field(default_factory=list)
    handovers: list[float] = field(default_factory=list)  # seconds each took
    max_pending_files: int = 0  # the most files waiting for the worker at once
    error: Optional[str] = None  # what stopped the run before its end
    reader_pauses: int = 0       # how often, and how long in all, the worker stood still (reader_pause)
    reader_paused_s: float = 0.0
    replay_published: int = 0
    exit_status: Optional[int] = None
    container_cpu_s: float = 0.0
    other_cpu_s: float = 0.0
    kernel_cpu_s: float = 0.0
    churn_s: float = 0.0
    peak_rss_mib: float = 0.0


class Churn:
    """One soak run (module docstring); ``run()`` returns a :class:`ChurnResult`."""

    def __init__(self, plan: SoakPlan, workdir: Path, node: Node, pool: Executor, log: Callable[[str], None],
                 keep_bags: bool = False) -> None:
        self.plan, self.workdir, self.node, self.pool, self.log = plan, workdir, node, pool, log
        self.reader = ReaderPause(pool.submit(os.getpid).result())
        self.next_backlog_check = 0.0
        self.keep_bags = keep_bags
        self.events_node = Node(f"soak_events_{os.getpid()}", context=node.context)
        self.events = SingleThreadedExecutor(context=node.context)
        self.events.add_node(self.events_node)
        # A container name of its own: a client of another run in the same ROS domain (a test's ContainerClient
        # of /ComponentManager) cannot load into this one, nor this run's client into theirs.
        self.container = f"soak_container_{os.getpid()}"
        self.client = ContainerClient(node, f"/{self.container}")
        (workdir / "links").mkdir()
        (workdir / "bags").mkdir()
        self.result = ChurnResult()
        self.collector = Collector(workdir / "links", pool, min(0.5, plan.split_s / 10), self.result.problems)
        self.process: Optional[ContainerProcess] = None
        self.recorder: Optional[RecorderRun] = None   # the one recording
        self.incoming: Optional[RecorderRun] = None   # the next one, during a hand-over
        self.retiring: Optional[RecorderRun] = None   # the previous one, being stopped
        self.extra: Optional[Extra] = None
        self.rig_ids: list[int] = []
        self.player_id = 0

    # --- the run ------------------------------------------------------------------------------------------
    def run(self) -> ChurnResult:
        """The run; one that cannot go on is stopped, with what it observed and ``error`` saying why."""
        try:
            self.start()
            self.churn()
            self.finish()
        except Exception as exc:  # noqa: BLE001 - the report says what stopped the run, and what it saw until then
            self.result.error = f"{type(exc).__name__}: {exc}"
            self.log(f"the run stopped: {self.result.error}")
        finally:
            self.reader.resume()
            self.result.reader_pauses, self.result.reader_paused_s = self.reader.pauses, self.reader.paused_s
            self.collector.stop()
            if self.process is not None:
                self.process.kill()
            self.client.destroy()
            self.events.shutdown()
            self.events_node.destroy_node()
        return self.result

    def start(self) -> None:
        plan = self.plan
        replay_bag = self.workdir / "replay_bag"
        write_replay_bag(replay_bag, plan.replay_messages, plan.replay_rate)
        first = self.recorder_component(0)
        startup = self.workdir / "startup.yaml"
        entries = [*plan.rig_components(), plan.player(replay_bag).startup_entry(), first.startup_entry()]
        startup.write_text(yaml.safe_dump({"components": entries}, sort_keys=False))
        self.process = ContainerProcess("--shutdown-timeout", f"{plan.shutdown_timeout_s:g}", "--load", str(startup),
                                        name=self.container, cwd=self.workdir, log_path=self.workdir / "container.log")
        self.client.wait(timeout=STARTUP_TIMEOUT)
        names = [f"/{entry['name']}" for entry in entries]
        listed = wait_until(lambda: self.listed(names), STARTUP_TIMEOUT)
        if not listed:
            raise RuntimeError(f"the container did not load {names}:\n{self.process.output[-3000:]}")
        self.rig_ids = [listed[f"/{entry['name']}"] for entry in plan.rig_components()]
        self.player_id = listed[f"/{PLAYER}"]
        self.recorder = self.track_recorder(0, first, listed[f"/{first.name}"])
        wait_until(lambda: REPLAY_TOPIC in self.recorder_topics(self.recorder), STARTUP_TIMEOUT)
        call(self.node, self.node.create_client(Resume, f"/{PLAYER}/resume"), timeout=30.0, again=True)

    def listed(self, names: list[str]) -> dict[str, int]:
        """The unique ids of ``names`` once the container lists every one of them; {} before."""
        ids = {name: uid for uid, name in self.client.listing()}
        return ids if all(name in ids for name in names) else {}

    def churn(self) -> None:
        plan = self.plan
        start = time.monotonic()
        cpu = cpu_seconds(self.process.pid)
        machine = machine_snapshot()
        next_extra, next_handover, next_poll = start, start + plan.handover_period_s, start
        end = start + plan.seconds
        self.log(f"churn: {plan.seconds:g} s, bags under {self.workdir / 'bags'}")
        while True:
            now = time.monotonic()
            if not self.process.alive():
                raise RuntimeError(f"the container exited during the churn:\n{self.process.output[-3000:]}")
            if self.extra is not None and now >= self.extra.unload_at:
                self.unload_extra()
            elif self.extra is None and now >= next_extra:
                if now >= end and self.incoming is None and self.retiring is None:
                    break
                self.sample(now - start)
                self.load_extra(now)
                next_extra += plan.extra_period_s
            self.step_recorders(now, now >= next_handover and now < end - 3 * plan.extra_period_s)
            if self.incoming is not None and next_handover <= now:
                next_handover += plan.handover_period_s
            if now >= next_poll:
                self.poll()
                next_poll += plan.split_s / 10
            self.events.spin_once(timeout_sec=0.02)
        self.result.churn_s = time.monotonic() - start
        self.result.container_cpu_s = cpu_seconds(self.process.pid) - cpu
        self.result.other_cpu_s, self.result.kernel_cpu_s = other_cpu(
            machine, machine_snapshot(), self.result.container_cpu_s, {self.process.pid, os.getpid()})

    def sample(self, t: float) -> None:
        """The container's resources now; a comparable moment (resources.Sample) when no recorder comes or goes,
        the recorder's backlog fits its cache and the memory of its last backlog in the stall reserve has gone
        back to the system (until then it is a disk stall's memory, not the container's)."""
        stats = self.recorder_stats(self.recorder)
        backlog = stats.get("backlog_bytes", 0)
        base = (self.incoming is None and self.retiring is None and backlog <= stats.get("max_cache_size", 0)
                and not stats.get("memory_return_pending", False))
        self.result.samples.append(Sample.take(self.process.pid, t, base, backlog))

    def finish(self) -> None:
        """The end (module docstring)."""
        if self.extra is not None:
            self.unload_extra()
        self.result.replay_published = self.stop_player()
        for unique_id in [self.player_id, *self.rig_ids]:
            self.unload(unique_id, "the player or a rig driver")
        self.result.peak_rss_mib = peak_rss_mb(self.process.pid)
        self.retiring, self.recorder = self.recorder, None
        self.send_stop(self.retiring)
        while self.retiring is not None:
            self.step_recorders(time.monotonic(), False)
            self.events.spin_once(timeout_sec=0.05)
        self.reader.resume()
        self.result.exit_status = self.process.stop(signal.SIGINT, timeout=STOP_TIMEOUT, check=False)
        if not wait_until(self.all_checked, READ_TIMEOUT, interval=0.2):
            self.result.problems.append(f"the worker had not read every file {READ_TIMEOUT:g} s after the end")

    def all_checked(self) -> bool:
        self.poll()
        return all(recorder.check is not None for recorder in self.result.recorders)

    # --- the extra driver ---------------------------------------------------------------------------------
    def load_extra(self, now: float) -> None:
        index = self.result.extra_instances
        component = self.plan.extra(index)
        response = self.client.load(component.plugin, name=component.name, parameters=component.parameters,
                                    extra=IPC, timeout=60.0)
        self.result.extra_instances += 1
        if not response.success:
            self.result.extra_load_failures.append(f"{component.name}: {response.error_message}")
            return
        self.extra = Extra(index, response.unique_id, now + self.plan.extra_alive_s)

    def unload_extra(self) -> None:
        self.unload(self.extra.unique_id, f"extra driver {self.extra.index}")
        self.extra = None

    def unload(self, unique_id: int, what: str) -> None:
        response = self.client.unload(unique_id, timeout=60.0)
        if not response.success:
            raise RuntimeError(f"unloading {what} (id {unique_id}) failed: {response.error_message}")

    # --- recorders ----------------------------------------------------------------------------------------
    def recorder_component(self, index: int) -> Component:
        return self.plan.recorder(index, self.workdir / "bags" / f"recorder_{index}")

    def track_recorder(self, index: int, component: Component, unique_id: int) -> RecorderRun:
        recorder = RecorderRun(index, component.name, Path(component.parameters["storage.uri"]), unique_id,
                               RecorderServices(self.node, component.name), time.monotonic())
        self.events_node.create_subscription(MessagesLostEvent, f"/{component.name}/events/messages_lost",
                                             recorder.on_lost_event, 10)
        with self.collector.lock:
            self.result.recorders.append(recorder)
            self.collector.recorders.append(recorder)
        return recorder

    def recorder_stats(self, recorder: RecorderRun) -> dict[str, Any]:
        """The recorder's live counts (``~/get_stats``' current bag)."""
        return recorder.services.stats().get("current") or {}

    def recorder_topics(self, recorder: RecorderRun) -> dict[str, Any]:
        return self.recorder_stats(recorder).get("topics", {})

    def step_recorders(self, now: float, handover_due: bool) -> None:
        """One step of the recorders' hand-over: begin one, wait for the incoming recorder's topics, wait for the
        retiring recorder's final counts, unload it."""
        if self.retiring is not None:
            self.step_retire(now)
        elif self.incoming is not None:
            self.step_handover(now)
        elif handover_due:
            self.begin_handover()

    def begin_handover(self) -> None:
        index = len(self.result.recorders)
        component = self.recorder_component(index)
        response = self.client.load(component.plugin, name=component.name, parameters=component.parameters,
                                    extra=IPC, timeout=60.0)
        if not response.success:
            raise RuntimeError(f"loading {component.name} failed: {response.error_message}")
        self.incoming = self.track_recorder(index, component, response.unique_id)

    def step_handover(self, now: float) -> None:
        """Once the incoming recorder has written every topic, the previous one is told to stop."""
        topics = self.recorder_topics(self.incoming)
        waiting = [t for t in self.plan.recorded_topics() if topics.get(t, {}).get("written", 0) == 0]
        if waiting:
            if now - self.incoming.loaded_at > 4 * self.plan.extra_period_s + 30.0:
                raise RuntimeError(f"{self.incoming.name} never recorded {waiting}")
            return
        self.result.handovers.append(now - self.incoming.loaded_at)
        self.retiring, self.recorder, self.incoming = self.recorder, self.incoming, None
        self.send_stop(self.retiring)

    def send_stop(self, recorder: RecorderRun) -> None:
        """``~/stop_recording``, from the node the churn spins: its reply (the final counts) comes once the
        backlog is written, which can take the container's whole unload bound."""
        client = self.events_node.create_client(Trigger, f"/{recorder.name}/stop_recording")
        if not client.wait_for_service(timeout_sec=30.0):
            raise RuntimeError(f"{recorder.name}: no ~/stop_recording service")
        recorder.stopping = (client, client.call_async(Trigger.Request()), time.monotonic())

    def step_retire(self, now: float) -> None:
        """The retiring recorder's final counts in: unload it, and collect its last files."""
        recorder = self.retiring
        client, future, sent = recorder.stopping
        if not future.done():
            if now - sent > 2 * self.plan.shutdown_timeout_s:
                raise RuntimeError(f"{recorder.name} did not answer ~/stop_recording")
            return
        recorder.finish(future.result())
        self.events_node.destroy_client(client)
        self.unload(recorder.unique_id, recorder.name)
        recorder.services.destroy()
        recorder.unloaded = True
        self.collector.collect()
        self.retiring = None

    def poll(self) -> None:
        """The files the worker has read taken in; checks of the bags whose files are all read; once a second,
        the worker stopped or continued by the recorder's backlog (reader_pause)."""
        if self.recorder is not None and time.monotonic() >= self.next_backlog_check:
            self.next_backlog_check = time.monotonic() + 1.0
            stats = self.recorder_stats(self.recorder)
            self.reader.update(stats.get("backlog_bytes", 0), stats.get("max_cache_size", 0))
        with self.collector.lock:
            pending = sum(len(recorder.pending) for recorder in self.result.recorders)
            self.result.max_pending_files = max(self.result.max_pending_files, pending)
            disk = os.statvfs(self.workdir)
            if disk.f_bavail * disk.f_frsize < MIN_FREE_BYTES:
                raise RuntimeError(f"less than {MIN_FREE_BYTES / 1e9:g} GB free on the bags' filesystem, "
                                   f"{pending} files waiting to be read: stopped")
            for recorder in self.result.recorders:
                recorder.harvest(self.result.union, self.result.problems)
                if recorder.ready_for_check():
                    recorder.check = check_bag(recorder)
                    discard(recorder, self.keep_bags)

    # --- the player ---------------------------------------------------------------------------------------
    def stop_player(self) -> int:
        """Pause the player and return how many messages it published once that count holds still."""
        call(self.node, self.node.create_client(Pause, f"/{PLAYER}/pause"), timeout=30.0, again=True)
        stats = self.node.create_client(Trigger, f"/{PLAYER}/get_stats")

        def published() -> int:
            reply = call(self.node, stats, timeout=30.0, again=True)
            return int(json.loads(reply.message)["published"].get(REPLAY_TOPIC, 0))

        counts = [published()]
        while True:
            time.sleep(2 / self.plan.replay_rate)
            counts.append(published())
            if counts[-1] == counts[-2]:
                return counts[-1]
