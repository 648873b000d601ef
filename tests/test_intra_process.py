"""The intra-process path with real rclpy nodes over Fast DDS.

"In the container" is a context holding the intra-process manager; "outside" is a second context, i.e. a
separate DDS participant that can only be reached over the wire (plus one test with a real second process).
"""
from __future__ import annotations

import subprocess
import threading
import sys
import time
import types
from typing import Any, Callable, Iterator

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from component_container import component_node
from component_container.component_executors import EXECUTOR_KINDS, make_component_executor
from component_container.component_node import REUSE_WATCH, ComponentNode, IntraProcessPublisher
from component_container.intra_process import IntraProcessManager

from container_process import ContainerClient, ContainerProcess
from ipc_testing.process_context import process_context


class Nodes:
    """The nodes a test makes in one context, destroyed with it: the process's context ("inside", the container's
    participant) or one of the test's own ("outside", another participant: a peer over DDS, as another process's
    would be). A node left to the garbage collector would keep its topics in the graph of later tests, and take
    its context's participant down at some random moment (ipc_testing/process_context.py)."""

    def __init__(self, own: bool) -> None:
        self.own = own
        if own:
            self.context = Context()
            rclpy.init(context=self.context)
        else:
            self.context = process_context()
        self.nodes: list[Node] = []

    def component(self, name: str, ipm: IntraProcessManager | None = None) -> ComponentNode:
        node = ComponentNode(name, context=self.context, intra_process_manager=ipm)
        self.nodes.append(node)
        return node

    def node(self, name: str) -> Node:
        node = Node(name, context=self.context)
        self.nodes.append(node)
        return node

    def close(self) -> None:
        for node in self.nodes:
            node.destroy_node()
        if self.own:
            rclpy.try_shutdown(context=self.context)


@pytest.fixture
def contexts() -> Iterator[tuple[Nodes, Nodes]]:
    """The nodes of the container ("inside") and of a peer over DDS ("outside"); the peer's participant exists
    only if the test makes a node there."""
    inside, outside = Nodes(own=False), Nodes(own=True)
    try:
        yield inside, outside
    finally:
        inside.close()
        outside.close()


@pytest.fixture
def ipm() -> IntraProcessManager:
    return IntraProcessManager()


def delivered(got: list[Any], published: list[Any], first_index: int = 0) -> bool:
    """The reuse rule: a publisher's first REUSE_WATCH messages arrive as equal copies, every later one as the
    very object that was published (``first_index``: the publish index of ``published[0]``)."""
    return len(got) == len(published) and all(
        (g is p) if i + first_index >= REUSE_WATCH else (g == p and g is not p)
        for i, (g, p) in enumerate(zip(got, published)))


def spin_until(executor: Any, condition: Callable[[], bool], timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        executor.spin_once(timeout_sec=0.05)
    return condition()


def test_subscriber_gets_the_very_object_published(contexts, ipm):
    inside, _ = contexts
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("sub", ipm)
    received: list[String] = []
    sub_node.create_subscription(String, "chatter", received.append, 10)
    publisher = pub_node.create_publisher(String, "chatter", 10)
    assert isinstance(publisher, IntraProcessPublisher)
    executor = SingleThreadedExecutor(context=inside.context)
    executor.add_node(sub_node)
    published = [String(data=f"m{i}") for i in range(5)]
    for msg in published:
        publisher.publish(msg)
    assert spin_until(executor, lambda: len(received) == 5)
    assert delivered(received, published)
    # Nobody outside: nothing was written to DDS (the publication log never advanced).
    assert publisher._publication.log._next_sequence == 1
    executor.shutdown()


def test_external_subscriber_gets_everything_and_local_one_no_duplicates(contexts, ipm):
    inside, outside = contexts
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("sub", ipm)
    external = outside.node("external")
    local_got: list[String] = []
    external_got: list[str] = []
    local = sub_node.create_subscription(String, "wire_chatter", local_got.append, 100)
    external_sub = external.create_subscription(String, "wire_chatter", lambda m: external_got.append(m.data), 100)
    # A plain DDS reader next to the in-process subscription: what reaches it over DDS reaches the in-process
    # subscription's own DDS reader too (same participant, same writer), which must not deliver it again.
    witness = inside.node("dds_witness")
    witness_got: list[str] = []
    witness_sub = witness.create_subscription(String, "wire_chatter", lambda m: witness_got.append(m.data), 100)
    publisher = pub_node.create_publisher(String, "wire_chatter", 100)
    inside_exec = SingleThreadedExecutor(context=inside.context)
    inside_exec.add_node(sub_node)
    inside_exec.add_node(witness)
    outside_exec = SingleThreadedExecutor(context=outside.context)
    outside_exec.add_node(external)
    # matched on both sides: the local DDS readers, the witness and the external one (a topic of its own: a
    # stale endpoint of an earlier test cannot count)
    assert spin_until(outside_exec, lambda: publisher.get_subscription_count() >= 3
                      and external_sub.get_publisher_count() >= 1, timeout=20)
    assert spin_until(inside_exec, lambda: witness_sub.get_publisher_count() >= 1
                      and local.dds_subscription.get_publisher_count() >= 1, timeout=20)
    published = [String(data=f"m{i}") for i in range(50)]
    for msg in published:
        publisher.publish(msg)
        time.sleep(0.002)
    assert spin_until(outside_exec, lambda: len(external_got) == 50, timeout=20)
    assert external_got == [m.data for m in published]
    assert spin_until(inside_exec, lambda: len(witness_got) == 50, timeout=20)
    assert len(local_got) == 50
    assert delivered(local_got, published)
    inside_exec.shutdown()
    outside_exec.shutdown()


def test_a_dds_sample_taken_after_its_publisher_was_destroyed_is_still_known_as_local(contexts, ipm):
    """An unload destroys a publisher whose last DDS samples may still wait in the local readers' queues (the
    executor had not taken them yet): they were delivered in-process already and must not come a second time."""
    inside, outside = contexts
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("sub", ipm)
    local_got: list[str] = []
    local = sub_node.create_subscription(String, "unloaded_chatter", lambda m: local_got.append(m.data), 100)
    # a reader outside, so that the publisher writes to DDS; a plain reader inside, to know when the local
    # readers have the samples (same participant, same writer)
    external = outside.node("external").create_subscription(String, "unloaded_chatter", lambda m: None, 100)
    witness_got: list[str] = []
    witness = inside.node("dds_witness")
    witness.create_subscription(String, "unloaded_chatter", lambda m: witness_got.append(m.data), 100)
    publisher = pub_node.create_publisher(String, "unloaded_chatter", 100)
    assert wait_for(lambda: publisher.get_subscription_count() >= 3 and external.get_publisher_count() >= 1
                    and local.dds_subscription.get_publisher_count() >= 1)
    for index in range(20):
        publisher.publish(String(data=f"m{index}"))
    assert local.received_count == 20  # queued in-process; nobody has spun yet
    pub_node.destroy_publisher(publisher)  # the unload, before the executor takes the DDS samples
    executor = SingleThreadedExecutor(context=inside.context)
    executor.add_node(sub_node)
    executor.add_node(witness)
    assert spin_until(executor, lambda: len(witness_got) == 20, timeout=20)
    spin_until(executor, lambda: False, timeout=0.3)  # what else the local subscription would take
    assert local_got == [f"m{index}" for index in range(20)]
    executor.shutdown()


def wait_for(condition: Callable[[], bool], timeout: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def test_external_publisher_reaches_in_process_subscriber(contexts, ipm):
    inside, outside = contexts
    sub_node = inside.component("sub", ipm)
    external = outside.node("external_pub")
    got: list[str] = []
    subscription = sub_node.create_subscription(String, "wire_inbound", lambda m: got.append(m.data), 100)
    publisher = external.create_publisher(String, "wire_inbound", 100)
    executor = SingleThreadedExecutor(context=inside.context)
    executor.add_node(sub_node)
    # matched on both sides (a topic of its own: a stale endpoint of an earlier test cannot count)
    assert spin_until(executor, lambda: publisher.get_subscription_count() >= 1
                      and subscription.dds_subscription.get_publisher_count() >= 1, timeout=20)
    for i in range(20):
        publisher.publish(String(data=f"x{i}"))
    assert spin_until(executor, lambda: len(got) == 20, timeout=20), got
    assert got == [f"x{i}" for i in range(20)]
    executor.shutdown()


def test_keep_last_queue_drops_oldest_and_counts(contexts, ipm):
    inside, _ = contexts
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("slow", ipm)
    got: list[String] = []
    subscription = sub_node.create_subscription(String, "chatter", got.append, 5)
    publisher = pub_node.create_publisher(String, "chatter", 10)
    published = [String(data=str(i)) for i in range(20)]
    for msg in published:  # the subscriber is not spinning: publish() must not wait for it
        publisher.publish(msg)
    executor = SingleThreadedExecutor(context=inside.context)
    executor.add_node(sub_node)
    assert spin_until(executor, lambda: len(got) == 5)
    assert not subscription.queue.queue  # nothing more to come: only DDS could add, and nobody is outside
    assert [m.data for m in got] == [str(i) for i in range(15, 20)]
    assert subscription.dropped_count == 15
    assert subscription.received_count == 20
    executor.shutdown()


def test_transient_local_late_joiner_gets_last_n(contexts, ipm):
    inside, _ = contexts
    latched = QoSProfile(depth=3, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub_node = inside.component("pub", ipm)
    publisher = pub_node.create_publisher(String, "map", latched)
    published = [String(data=str(i)) for i in range(5)]
    for msg in published:
        publisher.publish(msg)
    sub_node = inside.component("late", ipm)
    got: list[String] = []
    sub_node.create_subscription(String, "map", got.append, latched)
    # A plain DDS reader joining alike gets the DDS history (transient_local publishers always write to DDS);
    # once it has, the late subscription's own DDS reader has had it too, and must not deliver a second copy.
    witness = inside.node("dds_witness")
    witness_got: list[str] = []
    witness.create_subscription(String, "map", lambda m: witness_got.append(m.data), latched)
    executor = SingleThreadedExecutor(context=inside.context)
    executor.add_node(sub_node)
    executor.add_node(witness)
    assert spin_until(executor, lambda: len(got) >= 3 and witness_got == ["2", "3", "4"], timeout=20), witness_got
    assert len(got) == 3
    assert delivered(got, published[2:], first_index=2)
    executor.shutdown()


def test_fan_out_and_qos_compatibility(contexts, ipm):
    inside, _ = contexts
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("subs", ipm)
    reliable_got: list[list[String]] = [[], [], []]
    for sink in reliable_got:
        sub_node.create_subscription(String, "fan", sink.append, 10)
    best_effort_got: list[String] = []
    sub_node.create_subscription(String, "fan", best_effort_got.append, best_effort)
    reliable_pub = pub_node.create_publisher(String, "fan", 10)
    executor = SingleThreadedExecutor(context=inside.context)
    executor.add_node(sub_node)
    msg = String(data="shared")
    reliable_pub.publish(msg)
    assert spin_until(executor, lambda: all(reliable_got) and best_effort_got)
    # Everyone shares one object (a copy: it is the publisher's first message, see the reuse rule).
    assert all(sink == [msg] and sink[0] is reliable_got[0][0] for sink in reliable_got)
    assert best_effort_got[0] is reliable_got[0][0]
    # A best-effort publisher does not feed reliable subscriptions, only the best-effort one.
    lossy_pub = pub_node.create_publisher(String, "fan", best_effort)
    lossy = String(data="lossy")
    lossy_pub.publish(lossy)
    after = String(data="after")
    reliable_pub.publish(after)  # delivered after the lossy one: once it is in, the lossy one would be too
    assert spin_until(executor, lambda: all(len(sink) == 2 for sink in reliable_got) and len(best_effort_got) == 3)
    assert best_effort_got[1] == lossy and best_effort_got[2] == after
    assert all(sink[1] == after for sink in reliable_got)
    executor.shutdown()


@pytest.mark.parametrize("kind", EXECUTOR_KINDS)
def test_all_executor_models_deliver_in_process(contexts, kind):
    inside, _ = contexts
    executor = make_component_executor(kind, inside.context, thread_num=2)
    ipm = IntraProcessManager(make_wakeup=executor.make_wakeup)
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("sub", ipm)
    try:
        got: list[String] = []
        topic = f"chatter_{kind}"  # apart from every other test's chatter, so that only this publisher reaches it
        sub_node.create_subscription(String, topic, got.append, 1000)
        publisher = pub_node.create_publisher(String, topic, 10)
        executor.add(pub_node)
        executor.add(sub_node)
        published = [String(data=str(i)) for i in range(200)]
        for msg in published:
            publisher.publish(msg)
        deadline = time.monotonic() + 10
        while len(got) < 200 and time.monotonic() < deadline:
            time.sleep(0.02)
        data = [m.data for m in got]
        assert len(got) == 200, ("twice:", sorted({d for d in data if data.count(d) > 1}), "missing:",
                                 sorted(set(map(str, range(200))) - set(data)))
        assert delivered(sorted(got, key=lambda m: int(m.data)), published)
        executor.remove(sub_node)
        sub_node.destroy_node()
        publisher.publish(String(data="after unload"))  # nobody left: must not raise
    finally:
        executor.shutdown()
        for node in (sub_node, pub_node):  # a node left alive keeps its topic in the graph of later tests
            node.destroy_node()


def test_components_that_do_not_opt_in_use_plain_dds(contexts):
    inside, _ = contexts
    node = inside.component("plain")
    publisher = node.create_publisher(String, "chatter", 10)
    assert not isinstance(publisher, IntraProcessPublisher)
    assert not node.uses_intra_process


def _external_listener(count: int) -> subprocess.Popen:
    code = f"""
import rclpy, sys, time
from rclpy.node import Node
from std_msgs.msg import String
rclpy.init()
node = Node('external_listener')
got = []
node.create_subscription(String, '/chatter', lambda m: got.append(m.data), 1000)
deadline = time.monotonic() + 30
while len(got) < {count} and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.1)
print(len(got), len(set(got)), flush=True)
"""
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)


def test_container_process_talker_reaches_other_process_and_unload_under_traffic():
    with ContainerProcess("--use-intra-process-comms", "--executor", "multi") as container:
        listener_proc = _external_listener(40)
        node = Node("ipc_test_client", context=process_context())
        try:
            client = ContainerClient(node)
            client.wait()
            listener = client.load("components::Listener")
            talker = client.load("components::Talker", parameters={"rate": 50.0})
            assert listener.success and talker.success
            out, _ = listener_proc.communicate(timeout=40)
            received, distinct = map(int, out.split())
            assert received >= 40 and distinct == received  # over DDS, every message once
            assert client.unload(listener.unique_id).success  # while the talker keeps publishing
            assert client.unload(talker.unique_id).success
            assert list(client.list().unique_ids) == []
            assert container.alive()
        finally:
            if listener_proc.poll() is None:
                listener_proc.kill()
                listener_proc.wait()
            node.destroy_node()
        assert container.stop() == 0


def test_inline_subscription_runs_in_the_publishers_thread_without_executor(contexts, ipm):
    inside, _ = contexts
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("sink", ipm)
    got: list[tuple[String, dict, int]] = []
    subscription = sub_node.create_subscription(
        String, "chatter", lambda m, info: got.append((m, info, threading.get_ident())), 10,
        intra_process_inline=True)
    publisher = pub_node.create_publisher(String, "chatter", 10)
    msg = String(data="now")
    publisher.publish(msg)  # nobody spins: the callback has already run when publish() returns
    assert len(got) == 1 and got[0][0] == msg and got[0][2] == threading.get_ident()
    assert got[0][1]["received_timestamp"] >= got[0][1]["source_timestamp"] > 0
    assert subscription.received_count == 1 and subscription.dropped_count == 0


def test_subscriptions_joining_and_leaving_between_publishes_are_served_exactly(contexts, ipm):
    """The publisher's cached list of in-process targets follows every subscription created or destroyed."""
    inside, _ = contexts
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("sink", ipm)
    publisher = pub_node.create_publisher(String, "joiners", 10)
    first: list[str] = []
    second: list[str] = []
    a = sub_node.create_subscription(String, "joiners", lambda m: first.append(m.data), 10,
                                     intra_process_inline=True)
    publisher.publish(String(data="1"))
    sub_node.create_subscription(String, "joiners", lambda m: second.append(m.data), 10, intra_process_inline=True)
    publisher.publish(String(data="2"))
    sub_node.destroy_subscription(a)
    publisher.publish(String(data="3"))
    assert first == ["1", "2"] and second == ["2", "3"]
    assert publisher.local_subscription_count() == 1


def test_the_dds_reader_count_is_read_at_most_every_few_milliseconds(contexts, ipm, monkeypatch):
    """A publish reads the DDS reader count (6 us among the S3 drivers) only once DDS_COUNT_TTL_NS has passed."""
    inside, _ = contexts
    pub_node = inside.component("pub", ipm)
    publisher = pub_node.create_publisher(String, "counted", 10)
    now = [10 ** 12]
    monkeypatch.setattr(component_node, "time", types.SimpleNamespace(monotonic_ns=lambda: now[0]))
    reads: list[int] = []
    real_count = publisher.publisher.get_subscription_count
    monkeypatch.setattr(publisher.publisher, "get_subscription_count", lambda: reads.append(now[0]) or real_count())
    for _ in range(20):
        publisher.publish(String(data="x"))
        now[0] += 1_000_000  # 1 ms
    assert len(reads) == 4 and all(b - a == component_node.DDS_COUNT_TTL_NS for a, b in zip(reads, reads[1:]))


# --- supervision: races, bounds, reuse ----------------------------------------------------------------------
def test_unsubscribing_while_a_publisher_delivers_never_raises_into_it(contexts, ipm):
    """Destroying an in-process subscription while another thread publishes to it: the publisher must never
    see the subscription's destroyed guard condition (InvalidHandle inside its own publish())."""
    inside, _ = contexts
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("sub", ipm)
    publisher = pub_node.create_publisher(String, "race", 10)
    errors: list[BaseException] = []
    stop = threading.Event()

    def publish_forever() -> None:
        while not stop.is_set():
            try:
                publisher.publish(String(data="x"))
            except BaseException as exc:  # noqa: BLE001 - what the test is looking for
                errors.append(exc)
                return

    thread = threading.Thread(target=publish_forever)
    thread.start()
    try:
        for _ in range(300):
            subscription = sub_node.create_subscription(String, "race", lambda m: None, 10)
            time.sleep(0.0005)
            sub_node.destroy_subscription(subscription)
    finally:
        stop.set()
        thread.join()
    assert errors == []


def test_keep_all_queues_are_bounded_and_count_drops(contexts, ipm):
    inside, _ = contexts
    from rclpy.qos import HistoryPolicy
    from sensor_msgs.msg import Image

    from component_container.intra_process import KEEP_ALL_MAX_BYTES, KEEP_ALL_MAX_MESSAGES

    keep_all = QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1)
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("stalled", ipm)
    small = sub_node.create_subscription(String, "many", lambda m: None, keep_all)
    big = sub_node.create_subscription(Image, "frames", lambda m: None, keep_all)
    strings = pub_node.create_publisher(String, "many", keep_all)
    frames = pub_node.create_publisher(Image, "frames", keep_all)
    for i in range(KEEP_ALL_MAX_MESSAGES + 500):  # nobody spins: the subscriber is stalled
        strings.publish(String(data=str(i)))
    assert len(small.queue.queue) == KEEP_ALL_MAX_MESSAGES
    assert small.dropped_count == 500 and small.received_count == KEEP_ALL_MAX_MESSAGES + 500
    frame_bytes = 1920 * 1080 * 3
    for _ in range(KEEP_ALL_MAX_BYTES // frame_bytes + 20):
        frames.publish(Image(height=1080, width=1920, encoding="rgb8", step=1920 * 3, data=bytes(frame_bytes)))
    queued = len(big.queue.queue)  # as many frames as the byte limit holds: one more frame's data would not fit
    assert queued * frame_bytes <= KEEP_ALL_MAX_BYTES < (queued + 1) * frame_bytes, queued
    assert big.dropped_count == big.received_count - queued >= 20


def test_a_reused_message_object_is_copied_for_in_process_subscribers(contexts, ipm):
    inside, _ = contexts
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("sub", ipm)
    got: list[String] = []
    sub_node.create_subscription(String, "reused", got.append, 1000)
    publisher = pub_node.create_publisher(String, "reused", 1000)
    message = String()
    for i in range(100):  # one object, refilled and published again while the subscriber still holds it
        message.data = str(i)
        publisher.publish(message)
    executor = SingleThreadedExecutor(context=inside.context)
    executor.add_node(sub_node)
    assert spin_until(executor, lambda: len(got) == 100)
    assert [m.data for m in got] == [str(i) for i in range(100)]
    assert all(m is not message for m in got) and len({id(m) for m in got}) == 100
    assert publisher.reuses_messages
    executor.shutdown()


def test_a_pool_of_reused_objects_is_detected_and_fresh_objects_stay_zero_copy(contexts, ipm):
    inside, _ = contexts
    pub_node = inside.component("pub", ipm)
    sub_node = inside.component("sub", ipm)
    pooled: list[String] = []
    fresh: list[String] = []
    sub_node.create_subscription(String, "pooled", pooled.append, 1000)
    sub_node.create_subscription(String, "fresh", fresh.append, 1000)
    pool_publisher = pub_node.create_publisher(String, "pooled", 1000)
    fresh_publisher = pub_node.create_publisher(String, "fresh", 1000)
    pool = [String() for _ in range(REUSE_WATCH)]
    fresh_sent = [String(data=str(i)) for i in range(50)]
    for i in range(50):
        pool[i % REUSE_WATCH].data = str(i)
        pool_publisher.publish(pool[i % REUSE_WATCH])
        fresh_publisher.publish(fresh_sent[i])
    executor = SingleThreadedExecutor(context=inside.context)
    executor.add_node(sub_node)
    assert spin_until(executor, lambda: len(pooled) == 50 and len(fresh) == 50)
    assert [m.data for m in pooled] == [str(i) for i in range(50)]
    assert pool_publisher.reuses_messages and not fresh_publisher.reuses_messages
    assert delivered(fresh, fresh_sent)
    executor.shutdown()


def test_a_raising_inline_callback_is_reported_not_raised_into_the_publisher(contexts):
    inside, _ = contexts
    reported: list[tuple[Any, BaseException]] = []
    manager = IntraProcessManager(on_callback_error=lambda node, exc: reported.append((node, exc)))
    pub_node = inside.component("pub", manager)
    sub_node = inside.component("sink", manager)

    def broken(message: String) -> None:
        raise ValueError(f"cannot take {message.data}")

    sub_node.create_subscription(String, "inline", broken, 10, intra_process_inline=True)
    publisher = pub_node.create_publisher(String, "inline", 10)
    publisher.publish(String(data="this"))  # must not raise here
    assert len(reported) == 1 and reported[0][0] is sub_node
    assert str(reported[0][1]) == "cannot take this"
