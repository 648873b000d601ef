"""``--executor events`` in-process, with real rclpy nodes over Fast DDS: every callback kind supervised (the
same checks for every executor model), what rclpy 7.1.6's EventsExecutor cannot run refused cleanly, node
changes from other threads while it spins, unloads racing traffic, and a bounded shutdown.

See component_container/events_executor.py for why each of these needed work. The racing unloads are seeded:
a fixed seed and 50 cycles by default, a fresh seed and 150 cycles with ``make sweep``; the seed is printed and
``IPC_EXECUTOR_SEED`` replays it.
"""
from __future__ import annotations

import os
import pathlib
import random
import threading
import time
from typing import Any, Callable, Iterator

import pytest
import rclpy
import rclpy.executors
import rclpy.experimental
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.guard_condition import GuardCondition
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger

from component_container.component_executors import EXECUTOR_KINDS, ComponentExecutor, make_component_executor
from component_container.component_node import ComponentNode
from component_container.events_executor import UnsupportedByEventsExecutor
from component_container.intra_process import IntraProcessManager
from ipc_testing.process_context import process_context


class Harness:
    """One executor model in the process's context, recording what it reports."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.context = process_context()
        self.errors: list[tuple[str, BaseException]] = []
        self.fatal: list[tuple[str, BaseException]] = []
        self._lock = threading.Lock()
        self.executor: ComponentExecutor = make_component_executor(kind, self.context, 2, self._on_error,
                                                                   self._on_fatal)
        self.ipm = IntraProcessManager(on_callback_error=self._on_error, make_wakeup=self.executor.make_wakeup)
        self.nodes: list[Node] = []

    def _on_error(self, node: Node, exc: BaseException) -> None:
        with self._lock:
            self.errors.append((node.get_name(), exc))

    def _on_fatal(self, name: str, exc: BaseException) -> None:
        with self._lock:
            self.fatal.append((name, exc))

    def failed(self) -> dict[str, str]:
        """Node name -> the first error it reported."""
        with self._lock:
            first: dict[str, str] = {}
            for name, exc in self.errors:
                first.setdefault(name, str(exc))
            return first

    def node(self, name: str, ipc: bool = False) -> Node:
        node: Node = (ComponentNode(name, context=self.context, intra_process_manager=self.ipm) if ipc
                      else Node(name, context=self.context))
        self.nodes.append(node)
        return node

    def alive(self) -> bool:
        return bool(self.executor.threads()) and all(t.is_alive() for t in self.executor.threads())

    def close(self) -> None:
        for node in self.nodes:
            self.executor.remove(node, 1.0)
            node.destroy_node()
        self.executor.shutdown(2.0)


@pytest.fixture
def harness(request: pytest.FixtureRequest) -> Iterator[Harness]:
    made = Harness(request.param)
    yield made
    made.close()


def wait_for(condition: Callable[[], Any], timeout: float = 10.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        result = condition()
        if result:
            return result
        time.sleep(0.02)
    return condition()


def raising(kind: str) -> Callable[..., None]:
    def callback(*_args: Any) -> None:
        raise RuntimeError(f"deliberate failure in a {kind} callback")
    return callback


# --- exceptions in every kind of callback --------------------------------------------------------------------
@pytest.mark.parametrize("harness", EXECUTOR_KINDS, indirect=True)
def test_each_callback_kind_reports_its_exception_as_its_nodes_failure(harness: Harness) -> None:
    """One failing node per callback kind; each failure is attributed to its own node, and the healthy node
    next to them keeps running on the same thread."""
    feeder = harness.node("feeder", ipc=True)
    ticks: list[int] = []
    ipc_pub = feeder.create_publisher(String, "fault_ipc", 10)
    dds_pub = feeder.create_publisher(String, "fault_dds", 10)
    info_pub = feeder.create_publisher(String, "fault_info", 10)
    feeder.create_publisher(String, "fault_qos", QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    client = feeder.create_client(Trigger, "fault_service")
    requests: list[Any] = []

    def tick() -> None:
        ticks.append(1)
        for publisher in (ipc_pub, dds_pub, info_pub):
            publisher.publish(String(data=str(len(ticks))))
        if len(ticks) % 10 == 0 and client.service_is_ready():
            requests.append(client.call_async(Trigger.Request()))

    feeder.create_timer(0.02, tick)

    harness.node("timer").create_timer(0.02, raising("timer"))

    async def coroutine_timer() -> None:
        raising("coroutine timer")()
    harness.node("coroutine_timer").create_timer(0.02, coroutine_timer)
    harness.node("subscription").create_subscription(String, "fault_dds", raising("subscription"), 10)

    def with_info(message: String, info: dict) -> None:
        assert isinstance(message, String) and info["source_timestamp"] > 0, (message, info)
        raising("subscription with message info")()
    harness.node("info_subscription").create_subscription(String, "fault_info", with_info, 10)
    harness.node("ipc_subscription", ipc=True).create_subscription(
        String, "fault_ipc", raising("intra-process subscription"), 10)
    harness.node("service").create_service(Trigger, "fault_service", raising("service"))
    harness.node("waitable").create_subscription(
        String, "fault_qos", lambda _msg: None, 10,
        event_callbacks=SubscriptionEventCallbacks(incompatible_qos=raising("QoS event")))

    for node in harness.nodes:
        harness.executor.add(node)
    expected = {"timer": "timer", "coroutine_timer": "coroutine timer", "subscription": "subscription",
                "info_subscription": "subscription with message info",
                "ipc_subscription": "intra-process subscription", "service": "service", "waitable": "QoS event"}
    assert wait_for(lambda: set(harness.failed()) >= set(expected), 15.0), harness.failed()
    failed = harness.failed()
    assert {name: failed[name] for name in expected} == {
        name: f"deliberate failure in a {kind} callback" for name, kind in expected.items()}
    assert "feeder" not in failed and not harness.fatal, (failed, harness.fatal)
    count = len(ticks)
    assert wait_for(lambda: len(ticks) >= count + 5, 5.0), "the healthy node stopped with the failing ones"
    assert harness.alive()
    assert not any(request.done() for request in requests), "a service that raised must not answer"


@pytest.mark.parametrize("harness", EXECUTOR_KINDS, indirect=True)
def test_services_clients_and_message_info_work(harness: Harness) -> None:
    """The healthy paths the events executor needed fixes for: a client's response, a coroutine service, a
    subscription that takes message info."""
    server, caller = harness.node("server"), harness.node("caller")

    def answer(_request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = True, "plain"
        return response

    async def answer_later(_request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = True, "coroutine"
        return response

    server.create_service(Trigger, "plain", answer)
    server.create_service(Trigger, "coroutine", answer_later)
    infos: list[dict] = []
    server.create_subscription(String, "with_info", lambda _msg, info: infos.append(info), 10)
    publisher = caller.create_publisher(String, "with_info", 10)
    clients = [caller.create_client(Trigger, name) for name in ("plain", "coroutine")]
    harness.executor.add(server)
    harness.executor.add(caller)
    assert wait_for(lambda: all(c.service_is_ready() for c in clients))
    futures = [c.call_async(Trigger.Request()) for c in clients]
    assert wait_for(lambda: all(f.done() for f in futures)), "no response"
    assert [f.result().message for f in futures] == ["plain", "coroutine"]
    assert wait_for(lambda: publisher.get_subscription_count() == 1)
    publisher.publish(String(data="x"))
    assert wait_for(lambda: infos), "the subscription taking message info got nothing"
    assert infos[0]["publication_sequence_number"] >= 1
    assert not harness.errors and not harness.fatal, (harness.errors, harness.fatal)


def timer_argument(spin_once: Callable[[], None], node: Node) -> list[Any]:
    """What a timer callback that takes one parameter is called with, once."""
    given: list[Any] = []
    node.create_timer(0.01, lambda info=None: given.append(info) if not given else None)
    deadline = time.monotonic() + 10.0
    while not given and time.monotonic() < deadline:
        spin_once()
    return given


@pytest.mark.parametrize("harness", EXECUTOR_KINDS, indirect=True)
def test_a_timer_callback_with_a_parameter_gets_what_rclpys_executor_gives_it(harness: Harness) -> None:
    """rclpy 9's EventsExecutor calls a timer callback that has a parameter with a TimerInfo (its other executors,
    and rclpy 7's, with nothing): the container's executors, which supervise every callback through a wrapper,
    pass on exactly what the rclpy executor they are built on passes."""
    reference_node = harness.node("reference")
    reference = (rclpy.experimental.EventsExecutor(context=harness.context) if harness.kind == "events"
                 else rclpy.executors.SingleThreadedExecutor(context=harness.context))
    reference.add_node(reference_node)
    expected = timer_argument(lambda: reference.spin_once(timeout_sec=0.05), reference_node)
    reference.remove_node(reference_node)
    reference.shutdown()
    assert expected, "rclpy's own executor never called the timer"
    node = harness.node("timed")
    harness.executor.add(node)
    given = timer_argument(lambda: time.sleep(0.02), node)
    assert [type(value) for value in given] == [type(value) for value in expected]
    assert not harness.errors and not harness.fatal, (harness.errors, harness.fatal)


# --- what rclpy's EventsExecutor cannot run --------------------------------------------------------------------
@pytest.mark.parametrize("harness", ["events"], indirect=True)
def test_events_refuses_a_node_with_guard_conditions(harness: Harness) -> None:
    node = harness.node("guarded")
    node.create_guard_condition(lambda: None)
    with pytest.raises(UnsupportedByEventsExecutor, match=r"/guarded has guard conditions.*--executor single"):
        harness.executor.add(node)
    harness.nodes.remove(node)
    node.destroy_node()


@pytest.mark.parametrize("harness", ["events"], indirect=True)
def test_events_a_guard_condition_created_later_fails_only_its_component(harness: Harness) -> None:
    healthy = harness.node("healthy")
    ticks: list[int] = []
    healthy.create_timer(0.02, lambda: ticks.append(1))
    late = harness.node("late_guard")
    late_timer = late.create_timer(0.02, lambda: (late_timer.cancel(), late.create_guard_condition(lambda: None)))
    harness.executor.add(healthy)
    harness.executor.add(late)
    assert wait_for(lambda: "late_guard" in harness.failed())
    assert "guard conditions, which rclpy's EventsExecutor cannot run" in harness.failed()["late_guard"]
    count = len(ticks)
    assert wait_for(lambda: len(ticks) >= count + 5, 5.0)
    assert harness.alive() and not harness.fatal


# --- node changes while spinning ------------------------------------------------------------------------------
def racing_unloads(harness: Harness, seed: int, cycles: int) -> None:
    """``cycles`` components added and removed from another thread (sometimes before the executor got to them)
    while a 1 kHz publisher feeds each over DDS and in-process, each with a 1 kHz timer and a service; every
    removed one is destroyed at once, as an unload does."""
    print(f"IPC_EXECUTOR_SEED={seed}, {cycles} cycles")
    feeder = harness.node("cycle_feeder", ipc=True)
    ipc_pub = feeder.create_publisher(String, "cycle_ipc", 100)
    dds_pub = feeder.create_publisher(String, "cycle_dds", 100)
    fed: list[int] = []

    def feed() -> None:
        fed.append(1)
        ipc_pub.publish(String(data="i"))
        dds_pub.publish(String(data="d"))

    feeder.create_timer(0.001, feed)
    harness.executor.add(feeder)
    received: list[int] = []
    rng = random.Random(seed)
    for cycle in range(cycles):
        victim = ComponentNode(f"victim_{cycle}", context=harness.context, intra_process_manager=harness.ipm)
        victim.create_subscription(String, "cycle_ipc", lambda _m: received.append(1), 10)
        victim.create_subscription(String, "cycle_dds", lambda _m, _i: received.append(2), 10)
        victim.create_timer(0.001, lambda: None)
        victim.create_service(Trigger, f"victim_{cycle}/trigger", lambda _q, r: r)
        harness.executor.add(victim)
        time.sleep(rng.choice([0.0, 0.0, 0.002, 0.01, 0.03]))  # how far the executor gets with it: seeded
        assert harness.executor.remove(victim, 2.0), cycle
        victim.destroy_node()
        assert not harness.fatal and harness.alive(), (cycle, harness.fatal)
    assert received, "no victim ever received anything"
    count = len(fed)
    assert wait_for(lambda: len(fed) >= count + 50, 5.0), "the feeder stopped"
    assert not harness.errors and not harness.fatal, (harness.errors[:3], harness.fatal)


@pytest.mark.parametrize("harness", EXECUTOR_KINDS, indirect=True)
def test_unloads_racing_traffic_and_load_unload_cycles(harness: Harness) -> None:
    racing_unloads(harness, int(os.environ.get("IPC_EXECUTOR_SEED") or 12), 50)


@pytest.mark.sweep
@pytest.mark.parametrize("harness", EXECUTOR_KINDS, indirect=True)
def test_unloads_racing_traffic_and_load_unload_cycles_of_random_seeds(harness: Harness) -> None:
    racing_unloads(harness, int(os.environ.get("IPC_EXECUTOR_SEED") or random.randrange(1_000_000)), 150)


@pytest.mark.parametrize("harness", EXECUTOR_KINDS, indirect=True)
def test_in_process_delivery_before_and_after_the_node_runs(harness: Harness) -> None:
    """Transient-local messages reach a subscriber while its node is being constructed (before the executor
    runs it): they are delivered once it runs, exactly once, never to a node already removed. A witness node
    that runs all along subscribes to the same messages: what it got, the executor has had the chance to run."""
    latched = QoSProfile(depth=3, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publisher = harness.node("map_server", ipc=True).create_publisher(String, "map", latched)
    for index in range(5):
        publisher.publish(String(data=str(index)))
    witness, late = harness.node("witness", ipc=True), harness.node("late", ipc=True)
    seen: list[str] = []
    got: list[str] = []
    witness.create_subscription(String, "map", lambda m: seen.append(m.data), latched)
    late.create_subscription(String, "map", lambda m: got.append(m.data), latched)
    harness.executor.add(witness)
    assert wait_for(lambda: seen == ["2", "3", "4"]), seen
    assert got == [], "a callback ran before its node was added to the executor"
    harness.executor.add(late)
    assert wait_for(lambda: len(got) >= 3)
    publisher.publish(String(data="5"))  # after the history: a second copy of it would come before this
    assert wait_for(lambda: "5" in got and "5" in seen)
    assert got == ["2", "3", "4", "5"]
    harness.executor.remove(late, 1.0)
    for data in ("after", "after again"):
        publisher.publish(String(data=data))
    assert wait_for(lambda: seen[-1] == "after again"), seen
    assert got == ["2", "3", "4", "5"]
    assert not harness.errors and not harness.fatal


# --- spinning and stopping --------------------------------------------------------------------------------------
def context_switches(thread: threading.Thread) -> int:
    """How often the kernel has switched a thread of this process out so far (it waited, or was preempted)."""
    fields = dict(line.split(":", 1) for line in
                  pathlib.Path(f"/proc/self/task/{thread.native_id}/status").read_text().splitlines())
    return int(fields["voluntary_ctxt_switches"]) + int(fields["nonvoluntary_ctxt_switches"])


@pytest.mark.parametrize("harness", ["events"], indirect=True)
def test_events_thread_sleeps_when_idle_and_stops_within_the_timeout(harness: Harness) -> None:
    """Idle, the spinning thread waits (the kernel seldom has to switch it out), rather than polling (rclpy 7.1.6's
    spin() without a timeout keeps a core busy); a shutdown stops a busy one within its timeout."""
    node = harness.node("idle")
    ticks: list[int] = []
    node.create_subscription(String, "nobody_publishes", lambda _m: None, 10)
    node.create_timer(0.02, lambda: ticks.append(1))
    harness.executor.add(node)
    assert wait_for(lambda: len(ticks) >= 3)  # the node runs
    node.destroy_timer(next(iter(node.timers)))
    (thread,) = harness.executor.threads()
    before = context_switches(thread)
    # Half a second of nothing to do. What is counted does not depend on the machine's speed or load: a thread
    # waiting in a slice of the events executor is switched out at most once per SPIN_SLICE (1 s), a polling one
    # thousands of times (5924 measured with SPIN_SLICE 0).
    time.sleep(0.5)
    switches = context_switches(thread) - before
    assert switches <= 10, f"the idle events thread was switched out {switches} times in half a second"
    assert harness.alive()
    busy = harness.node("busy")
    busy_ticks: list[int] = []
    busy.create_timer(0.001, lambda: busy_ticks.append(1))
    harness.executor.add(busy)
    assert wait_for(lambda: len(busy_ticks) >= 10)
    harness.executor.shutdown(2.0)
    assert not any(thread.is_alive() for thread in harness.executor.threads()), "still running after 2 s"
    assert not harness.fatal


class HeldGuardCondition(GuardCondition):
    """A guard condition that holds the first thread other than the test's to read its handle until
    :meth:`release`. An executor reads a guard condition's handle first when it enters the handles of the wait
    set it has just gathered, after it took its own guard condition into that set: holding the thread there is
    a preemption at that moment, made certain."""

    def __init__(self, node: Node) -> None:
        super().__init__(None, node.default_callback_group, context=node.context)
        self.reached = threading.Event()
        self._released = threading.Event()
        self._main = threading.current_thread()
        node.default_callback_group.add_entity(self)
        node._guards.append(self)  # as Node.create_guard_condition does, with this class

    @property
    def handle(self) -> Any:
        if threading.current_thread() is not self._main and not self.reached.is_set():
            self.reached.set()
            self._released.wait(10.0)
        return super().handle

    def release(self) -> None:
        self._released.set()


@pytest.mark.parametrize("harness", ["single", "multi", "isolated"], indirect=True)
def test_a_stop_while_the_thread_gathers_its_wait_set_ends_the_thread(harness: Harness) -> None:
    """Stopping a wait-set executor ends its thread even when the stop lands while that thread gathers its next
    wait set, and then nothing holds the node's entities any more: destroying the node destroys them at once.

    rclpy's ``Executor.shutdown()`` destroys the guard condition that wakes the wait set; a thread that had
    already taken it into the set it was gathering waited without it, forever (nothing else of this node
    becomes ready), holding the handles of the node's entities while the node was destroyed under it (found
    while looking for an intermittent hang of test_intra_process's executor-model test at ``destroy_node``)."""
    node = harness.node("held", ipc=True)
    subscription = node.create_subscription(String, "nobody_publishes_here", lambda _m: None, 10)
    harness.executor.add(node)
    held = HeldGuardCondition(node)
    node._wake_executor()  # the executor gathers a wait set that holds the new guard condition
    (thread,) = harness.executor.threads()
    try:
        assert held.reached.wait(10.0), "the executor never gathered a wait set with the guard condition"
        stopping = threading.Thread(target=harness.executor.shutdown, args=(5.0,))
        stopping.start()
        # Let a stop that shuts rclpy's executor down first do so while the thread is held (it does at once); a
        # stop that waits for the thread first is still waiting when this gives up.
        wait_for(lambda: thread.is_alive() and _rclpy_executor_shut_down(harness, node), timeout=0.5)
        held.release()
        stopping.join(10.0)
        assert not stopping.is_alive()
        assert not thread.is_alive(), "the executor thread still waits after its executor was stopped"
        node.destroy_node()
        assert subscription.handle.pointer == 0, "something still holds the subscription of a destroyed node"
    finally:
        held.release()
        if thread.is_alive():  # left waiting (the failure above): woken, so that it does not outlive the test
            held.trigger()
            thread.join(5.0)
    assert not harness.fatal and not harness.failed()


def _rclpy_executor_shut_down(harness: Harness, node: Node) -> bool:
    """Whether the rclpy executor running ``node`` has been shut down (its guard condition destroyed)."""
    executor = node.executor
    return executor is not None and executor._guard is None
