#!/usr/bin/env python3
"""Intra-process vs. DDS transport: messages per second and delivery latency, side by side in one run.

Modes (every one measured for each message kind):

* ``intra-process``: two :class:`ComponentNode` s sharing an :class:`IntraProcessManager` in one context;
  the subscriber is spun by the container's single-threaded executor model on its own thread. The
  subscriber's callback gets the very object that was published (no serialization, no copy).
* ``dds in-process``: two plain rclpy nodes in one context (one DDS participant), same executor model.
* ``dds cross-process``: the publisher here, the subscriber in a child process started by this script
  (``--child``), driven by JSON lines on its stdin and reporting its measurements as JSON lines on stdout.

Messages: a 1920x1080 ``rgb8`` ``sensor_msgs/Image`` (6 220 800 data bytes; each message gets its own data,
a ``bytes`` slice of a pre-made random pool assigned to the ``uint8[]`` field -- never a numpy array, which
rclpy converts element by element) and a small ``sensor_msgs/Imu``.

Runs per mode and message, on a fresh topic, QoS reliable / keep_last ``--depth`` (10) / volatile:

* warm-up: a few paced messages, discarded;
* ``burst``: ``--count`` images (``--small-count`` IMU messages) published as fast as possible, message
  construction included. keep_last lets a slow reader lose messages (the intra-process queue drops its
  oldest, DDS overwrites its history), so delivered/published is reported. msgs/s = delivered / (last
  delivery - first publish); MB/s = msgs/s x CDR-serialized message size (for intra-process no byte moves:
  it is the equivalent rate). Burst latency includes queueing behind earlier messages. In one process the
  publishing loop holds the GIL almost all the time, so an in-process subscriber thread gets to run about
  once per switch interval (5 ms) and takes what its queue of ``depth`` messages holds then: the in-process
  delivered counts of small messages measure that, not the transport;
* ``paced``: ``--rate`` Hz (30) for ``--duration`` seconds, each message built half a period before its
  tick: the delivery latency without backlog (as long as the subscriber keeps up with the rate).

``publish() ms`` is the mean duration of the ``publish()`` call itself (message construction excluded).

Latency = receive time in the subscriber callback (``time.time_ns()``) minus ``header.stamp``, which is set
from ``time.time_ns()`` just before ``publish()`` (same clock in both processes).

Isolation: ``ROS_DOMAIN_ID`` is set to a random 1..100 unless already set, and
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``, before rclpy is imported (benchmarks/isolation.py); the child gets
the same environment.
The child is always stopped by pid (and exits by itself when its stdin closes).

    python benchmarks/ipc_transport.py             # full run (about 40 s on 2 cores)
    python benchmarks/ipc_transport.py --quick     # smoke run (about 15 s)
    python benchmarks/ipc_transport.py --json      # machine-readable results on stdout
"""
from __future__ import annotations

import isolation  # noqa: F401  (first: the ROS environment before rclpy is imported)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import queue  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from typing import Any, Callable, Optional  # noqa: E402

import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402
from sensor_msgs.msg import Image, Imu  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

WIDTH, HEIGHT, BYTES_PER_PIXEL = 1920, 1080, 3
FRAME_BYTES = WIDTH * HEIGHT * BYTES_PER_PIXEL
POOL_EXTRA = 1 << 20          # the pool is one frame plus this; frame n starts at a rolling offset
OFFSET_STRIDE = 4099
WARMUP_MESSAGES = 5
MATCH_TIMEOUT = 15.0          # seconds to wait for DDS discovery
QUIET_SECONDS = 1.0           # a collection ends when nothing more arrived for this long ...
COLLECT_TIMEOUT = 15.0        # ... or at the latest after this long
CHILD_REPLY_TIMEOUT = COLLECT_TIMEOUT + 15.0

MODES = ("intra-process", "dds in-process", "dds cross-process")
MESSAGES = ("image", "imu")
MESSAGE_LABELS = {"image": "Image 1920x1080 rgb8", "imu": "Imu"}
MESSAGE_TYPES = {"image": Image, "imu": Imu}


def log(text: str) -> None:
    print(f"[ipc_transport] {text}", file=sys.stderr, flush=True)


def bench_qos(depth: int) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)


def init_context() -> Context:
    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    return context


# ---------------------------------------------------------------------------------------------- messages
class ImageFactory:
    """Fresh 1080p rgb8 images whose data is a ``bytes`` slice of one pre-made random pool."""

    def __init__(self) -> None:
        self._pool = np.random.default_rng(0x1BC).bytes(FRAME_BYTES + POOL_EXTRA)  # bytes, made once
        self._offsets = POOL_EXTRA + 1

    def make(self, sequence: int) -> Image:
        offset = (sequence * OFFSET_STRIDE) % self._offsets
        data = self._pool[offset:offset + FRAME_BYTES]  # bytes: one memcpy
        return Image(header=Header(frame_id="camera"), height=HEIGHT, width=WIDTH, encoding="rgb8",
                     is_bigendian=0, step=WIDTH * BYTES_PER_PIXEL, data=data)  # bytes -> array('B'): memcpy


class ImuFactory:
    def make(self, sequence: int) -> Imu:
        msg = Imu(header=Header(frame_id="imu"))
        msg.orientation.w = 1.0
        msg.linear_acceleration.z = 9.81
        msg.angular_velocity.x = sequence * 1e-3
        return msg


def stamp_now(msg: Any) -> None:
    """header.stamp := now (time.time_ns()), right before publish()."""
    sec, nanosec = divmod(time.time_ns(), 1_000_000_000)
    stamp = msg.header.stamp
    stamp.sec = sec
    stamp.nanosec = nanosec


# ---------------------------------------------------------------------------------------------- receiving
class Receiver:
    """Subscriber callback: records (receive time, latency) per message; collect() hands them over."""

    def __init__(self) -> None:
        self._samples: list[tuple[int, int]] = []

    def callback(self, msg: Any) -> None:
        now = time.time_ns()
        stamp = msg.header.stamp
        self._samples.append((now, now - (stamp.sec * 1_000_000_000 + stamp.nanosec)))

    def collect(self, expected: int, quiet: float = QUIET_SECONDS, timeout: float = COLLECT_TIMEOUT) -> dict:
        """Wait for ``expected`` messages, or until none arrived for ``quiet`` s, or ``timeout``; then reset."""
        deadline = time.monotonic() + timeout
        seen, last_change = len(self._samples), time.monotonic()
        while True:
            count = len(self._samples)
            now = time.monotonic()
            if count != seen:
                seen, last_change = count, now
            if count >= expected or now - last_change >= quiet or now >= deadline:
                break
            time.sleep(0.005)
        samples, self._samples = self._samples, []
        return {"count": len(samples),
                "first_ns": samples[0][0] if samples else None,
                "last_ns": samples[-1][0] if samples else None,
                "latencies_ns": [latency for _, latency in samples]}


def spin_thread(executor: SingleThreadedExecutor, stop: threading.Event) -> threading.Thread:
    def run() -> None:
        while not stop.is_set() and executor.context.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except Exception:  # context shut down under the executor
                if executor.context.ok() and not stop.is_set():
                    raise
                return

    thread = threading.Thread(target=run, name="bench-spin", daemon=True)
    thread.start()
    return thread


# ---------------------------------------------------------------------------------------------- child side
def child_main() -> int:
    """The cross-process subscriber: JSON commands on stdin, JSON replies on stdout, exits on EOF."""
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    context = init_context()
    executor = SingleThreadedExecutor(context=context)
    stop = threading.Event()
    spinner = spin_thread(executor, stop)
    receiver = Receiver()
    node: Optional[Node] = None
    out = sys.stdout

    def reply(payload: dict) -> None:
        out.write(json.dumps(payload) + "\n")
        out.flush()

    reply({"op": "ready", "pid": os.getpid(), "domain": os.environ.get("ROS_DOMAIN_ID")})
    try:
        for line in sys.stdin:
            command = json.loads(line)
            op = command["op"]
            if op == "subscribe":
                node = Node(f"ipc_bench_child_{command['kind']}", context=context)
                node.create_subscription(MESSAGE_TYPES[command["kind"]], command["topic"], receiver.callback,
                                         bench_qos(command["depth"]))
                executor.add_node(node)
                reply({"op": op})
            elif op == "collect":
                reply({"op": op, **receiver.collect(command["expected"], command.get("quiet", QUIET_SECONDS),
                                                     command.get("timeout", COLLECT_TIMEOUT))})
            elif op == "unsubscribe":
                if node is not None:
                    executor.remove_node(node)
                    node.destroy_node()
                    node = None
                reply({"op": op})
            elif op == "exit":
                break
    finally:
        stop.set()
        spinner.join(timeout=2)
        executor.shutdown(timeout_sec=1)
        rclpy.try_shutdown(context=context)
    return 0


class ChildSubscriber:
    """Parent-side handle of the child process."""

    def __init__(self) -> None:
        self._stderr = tempfile.TemporaryFile(mode="w+")
        self.process = subprocess.Popen(
            [sys.executable, os.path.abspath(__file__), "--child"], env=os.environ.copy(),
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._stderr, text=True, bufsize=1,
            start_new_session=True)  # a terminal Ctrl-C reaches only us; we stop the child ourselves
        self._lines: queue.Queue[Optional[str]] = queue.Queue()
        threading.Thread(target=self._read, name="child-stdout", daemon=True).start()
        self._ready: Optional[dict] = None

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self._lines.put(line)
        self._lines.put(None)

    def _receive(self, op: str, timeout: float) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self._lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise RuntimeError(f"child subscriber: no '{op}' reply within {timeout:.0f} s") from None
            if line is None:
                raise RuntimeError(f"child subscriber exited (code {self.process.poll()}):\n{self.stderr_tail()}")
            reply = json.loads(line)
            if reply.get("op") == op:
                return reply

    def wait_ready(self, timeout: float = 30.0) -> dict:
        if self._ready is None:
            self._ready = self._receive("ready", timeout)
        return self._ready

    def request(self, op: str, timeout: float = CHILD_REPLY_TIMEOUT, **arguments: Any) -> dict:
        self.wait_ready()
        assert self.process.stdin is not None
        self.process.stdin.write(json.dumps({"op": op, **arguments}) + "\n")
        self.process.stdin.flush()
        return self._receive(op, timeout)

    def stderr_tail(self, chars: int = 2000) -> str:
        self._stderr.seek(0)
        return self._stderr.read()[-chars:]

    def stop(self) -> None:
        """Ask the child to exit, then terminate (and if need be kill) it by pid; always reaped."""
        process = self.process
        try:
            if process.poll() is None and process.stdin is not None:
                process.stdin.write(json.dumps({"op": "exit"}) + "\n")
                process.stdin.close()
        except (BrokenPipeError, OSError, ValueError):
            pass
        for sig, grace in ((None, 3.0), (signal.SIGTERM, 3.0), (signal.SIGKILL, 5.0)):
            if process.poll() is not None:
                break
            if sig is not None:
                try:
                    os.kill(process.pid, sig)
                except ProcessLookupError:
                    break
            try:
                process.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                continue
        self._stderr.close()


# ---------------------------------------------------------------------------------------------- parent side
@dataclass
class Setup:
    """One mode's publisher plus how to collect what its subscriber received."""

    publish: Callable[[Any], None]
    collect: Callable[[int], dict]
    close: Callable[[], None]
    extra: Callable[[], dict] = field(default=lambda: {})


def setup_in_process(mode: str, kind: str, topic: str, depth: int) -> Setup:
    # Imported here so that the child process does not need the container package.
    from component_container.component_executors import make_component_executor
    from component_container.component_node import ComponentNode
    from component_container.intra_process import IntraProcessManager

    context = init_context()
    receiver = Receiver()
    if mode == "intra-process":
        manager = IntraProcessManager()
        pub_node: Node = ComponentNode("ipc_bench_pub", intra_process_manager=manager, context=context)
        sub_node: Node = ComponentNode("ipc_bench_sub", intra_process_manager=manager, context=context)
    else:
        pub_node = Node("ipc_bench_pub", context=context)
        sub_node = Node("ipc_bench_sub", context=context)
    subscription = sub_node.create_subscription(MESSAGE_TYPES[kind], topic, receiver.callback, bench_qos(depth))
    publisher = pub_node.create_publisher(MESSAGE_TYPES[kind], topic, bench_qos(depth))
    executor = make_component_executor("single", context, thread_num=1)
    executor.add(sub_node)
    if mode != "intra-process":
        wait_for_match(publisher)

    def extra() -> dict:
        if mode != "intra-process":
            return {}
        log_ = getattr(getattr(publisher, "_publication", None), "log", None)
        return {"dds_writes": getattr(log_, "_next_sequence", 1) - 1,
                "ipc_dropped": getattr(subscription, "dropped_count", None)}

    def close() -> None:
        executor.shutdown()
        pub_node.destroy_node()
        sub_node.destroy_node()
        rclpy.try_shutdown(context=context)

    return Setup(publisher.publish, lambda expected: receiver.collect(expected), close, extra)


def setup_cross_process(kind: str, topic: str, depth: int, child: ChildSubscriber) -> Setup:
    context = init_context()
    pub_node = Node("ipc_bench_pub", context=context)
    publisher = pub_node.create_publisher(MESSAGE_TYPES[kind], topic, bench_qos(depth))
    child.request("subscribe", topic=topic, kind=kind, depth=depth)
    try:
        wait_for_match(publisher)
    except Exception:
        pub_node.destroy_node()
        rclpy.try_shutdown(context=context)
        raise

    def close() -> None:
        try:
            child.request("unsubscribe")
        finally:
            pub_node.destroy_node()
            rclpy.try_shutdown(context=context)

    return Setup(publisher.publish,
                 lambda expected: child.request("collect", expected=expected, quiet=QUIET_SECONDS,
                                                timeout=COLLECT_TIMEOUT),
                 close)


def wait_for_match(publisher: Any) -> None:
    deadline = time.monotonic() + MATCH_TIMEOUT
    while publisher.get_subscription_count() < 1:
        if time.monotonic() > deadline:
            raise RuntimeError(f"no subscriber matched {publisher.topic_name} within {MATCH_TIMEOUT:.0f} s")
        time.sleep(0.02)
    time.sleep(0.2)  # let the reader side finish matching as well


def publish_burst(setup: Setup, factory: Any, count: int, max_seconds: float) -> dict:
    durations: list[int] = []
    deadline = time.monotonic() + max_seconds
    start = time.time_ns()
    for sequence in range(count):
        msg = factory.make(sequence)
        stamp_now(msg)
        before = time.perf_counter_ns()
        setup.publish(msg)
        durations.append(time.perf_counter_ns() - before)
        del msg  # after publish() the message belongs to the subscribers
        if time.monotonic() > deadline:
            break
    return {"start_ns": start, "end_ns": time.time_ns(), "publish_call_ns": durations}


def publish_paced(setup: Setup, factory: Any, rate: float, seconds: float, first_sequence: int = 0) -> dict:
    durations: list[int] = []
    period = 1.0 / rate
    count = max(1, round(rate * seconds))
    start = time.time_ns()
    tick = time.perf_counter() + period / 2
    for i in range(count):
        # Built half a period before its tick, so that building (which holds the GIL: two 6 MB copies for
        # an image) does not delay the delivery of the previous message; stamped at the tick.
        sleep_until(tick - period / 2)
        msg = factory.make(first_sequence + i)
        sleep_until(tick)
        stamp_now(msg)
        before = time.perf_counter_ns()
        setup.publish(msg)
        durations.append(time.perf_counter_ns() - before)
        del msg
        tick += period
    return {"start_ns": start, "end_ns": time.time_ns(), "publish_call_ns": durations}


def sleep_until(deadline: float) -> None:
    delay = deadline - time.perf_counter()
    if delay > 0:
        time.sleep(delay)


def summarize(mode: str, kind: str, run: str, published: dict, received: dict, size: int) -> dict:
    latencies = np.asarray(received["latencies_ns"], dtype=np.float64) / 1e6
    delivered = received["count"]
    n_published = len(published["publish_call_ns"])
    end = max(published["end_ns"], received["last_ns"] or 0)
    elapsed = (end - published["start_ns"]) / 1e9
    rate = delivered / elapsed if elapsed > 0 else 0.0
    publish_seconds = (published["end_ns"] - published["start_ns"]) / 1e9
    calls = np.asarray(published["publish_call_ns"], dtype=np.float64) / 1e6

    def pct(q: float) -> Optional[float]:
        return float(np.percentile(latencies, q)) if latencies.size else None

    return {
        "mode": mode, "message": kind, "label": MESSAGE_LABELS[kind], "run": run,
        "message_bytes": size, "published": n_published, "delivered": delivered,
        "elapsed_s": elapsed, "msgs_per_s": rate, "mb_per_s": rate * size / 1e6,
        "publish_rate": n_published / publish_seconds if publish_seconds > 0 else None,
        "publish_call_ms_mean": float(calls.mean()) if calls.size else None,
        "publish_call_ms_p99": float(np.percentile(calls, 99)) if calls.size else None,
        "latency_ms": {"p50": pct(50), "p90": pct(90), "p99": pct(99),
                       "min": float(latencies.min()) if latencies.size else None,
                       "max": float(latencies.max()) if latencies.size else None,
                       "mean": float(latencies.mean()) if latencies.size else None},
    }


def run_one(mode: str, kind: str, args: argparse.Namespace, child: Optional[ChildSubscriber],
            factories: dict, sizes: dict, tag: str) -> list[dict]:
    topic = f"/ipc_bench_{tag}/{mode.replace(' ', '_').replace('-', '_')}/{kind}"
    count = args.count if kind == "image" else args.small_count
    if mode == "dds cross-process":
        assert child is not None
        setup = setup_cross_process(kind, topic, args.depth, child)
    else:
        setup = setup_in_process(mode, kind, topic, args.depth)
    factory = factories[kind]
    rows = []
    try:
        publish_paced(setup, factory, 20.0, WARMUP_MESSAGES / 20.0)
        setup.collect(WARMUP_MESSAGES)
        counters = setup.extra()
        burst = publish_burst(setup, factory, count, args.max_burst_seconds)
        rows.append(summarize(mode, kind, "burst", burst, setup.collect(len(burst["publish_call_ns"])),
                              sizes[kind]))
        counters = add_counter_deltas(rows[-1], counters, setup.extra())
        paced = publish_paced(setup, factory, args.rate, args.duration, first_sequence=count)
        rows.append(summarize(mode, kind, f"{args.rate:g} Hz", paced, setup.collect(len(paced["publish_call_ns"])),
                              sizes[kind]))
        add_counter_deltas(rows[-1], counters, setup.extra())
    finally:
        setup.close()
    for row in rows:
        log(f"{mode:17s} {kind:5s} {row['run']:6s} delivered {row['delivered']}/{row['published']} "
            f"{row['msgs_per_s']:.0f} msg/s p50 {fmt(row['latency_ms']['p50'])} ms")
    return rows


def add_counter_deltas(row: dict, before: dict, after: dict) -> dict:
    """Intra-process counters of this run only: DDS writes (should be 0) and keep_last queue drops."""
    row.update({name: value - before.get(name, 0) for name, value in after.items() if value is not None})
    return after


def fmt(value: Optional[float], digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def markdown_table(rows: list[dict]) -> str:
    lines = ["| mode | message | run | published | delivered | msgs/s | MB/s | latency p50 ms | p99 ms "
             "| publish() ms |",
             "|---|---|---|--:|--:|--:|--:|--:|--:|--:|"]
    for row in rows:
        lines.append(
            f"| {row['mode']} | {row['label']} | {row['run']} | {row['published']} | {row['delivered']} "
            f"| {row['msgs_per_s']:.0f} | {row['mb_per_s']:.1f} | {fmt(row['latency_ms']['p50'])} "
            f"| {fmt(row['latency_ms']['p99'])} | {fmt(row['publish_call_ms_mean'], 3)} |")
    return "\n".join(lines)


def parse_args(argv: Optional[list[str]] = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=None, help="images per burst (default 200, quick 30)")
    parser.add_argument("--small-count", type=int, default=None,
                        help="IMU messages per burst (default 20000, quick 2000)")
    parser.add_argument("--duration", type=float, default=None,
                        help="seconds of the paced run (default 4, quick 1)")
    parser.add_argument("--rate", type=float, default=30.0, help="paced publishing rate in Hz (default 30)")
    parser.add_argument("--depth", type=int, default=10, help="keep_last depth of every endpoint (default 10)")
    parser.add_argument("--max-burst-seconds", type=float, default=20.0,
                        help="a burst stops publishing after this long even if --count is not reached")
    parser.add_argument("--modes", default=",".join(MODES), help=f"comma-separated subset of: {', '.join(MODES)}")
    parser.add_argument("--messages", default=",".join(MESSAGES), help="comma-separated subset of: image, imu")
    parser.add_argument("--quick", action="store_true", help="short smoke run")
    parser.add_argument("--json", action="store_true", help="print the results as JSON instead of a table")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    defaults = {"count": (30, 200), "small_count": (2000, 20000), "duration": (1.0, 4.0)}
    for name, (quick, full) in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
    args.modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    args.messages = [m.strip() for m in args.messages.split(",") if m.strip()]
    for mode in args.modes:
        if mode not in MODES:
            parser.error(f"unknown mode {mode!r}")
    for kind in args.messages:
        if kind not in MESSAGES:
            parser.error(f"unknown message {kind!r}")
    if args.count < 1 or args.small_count < 1 or args.duration <= 0 or args.rate <= 0 or args.depth < 1:
        parser.error("--count, --small-count, --duration, --rate and --depth must be positive")
    return args


def reuse_check_cost(count: int = 20_000, repeats: int = 5) -> dict[str, float]:
    """publish() of fresh Imu objects to an inline in-process subscriber, with the reuse rule (see
    ComponentNode's IntraProcessPublisher) and with it switched off, interleaved; best of ``repeats``.

    What the rule costs the zero-copy path: a few identity checks and reference counts per publish.
    """
    from component_container.component_node import ComponentNode, IntraProcessPublisher
    from component_container.intra_process import IntraProcessManager

    class UncheckedPublisher(IntraProcessPublisher):
        def _must_copy(self, msg: Any) -> bool:
            return False

    context = init_context()
    node = ComponentNode("reuse_bench", intra_process_manager=IntraProcessManager(), context=context)
    node.create_subscription(Imu, "reuse_bench", lambda m: None, 10, intra_process_inline=True)
    checked = node.create_publisher(Imu, "reuse_bench", 10)
    unchecked = UncheckedPublisher(checked.publisher, IntraProcessManager(), node.get_logger())
    unchecked._manager = checked._manager  # same subscriber, same delivery path
    best = {"checked": float("inf"), "unchecked": float("inf")}
    for _ in range(repeats):
        for name, publisher in (("checked", checked), ("unchecked", unchecked)):
            messages = [Imu() for _ in range(count)]
            start = time.perf_counter_ns()
            for message in messages:
                publisher.publish(message)
            best[name] = min(best[name], (time.perf_counter_ns() - start) / count)
            del messages
    node.destroy_node()
    rclpy.try_shutdown(context=context)
    return {"publish_ns_with_reuse_check": best["checked"], "publish_ns_without": best["unchecked"],
            "ratio": best["checked"] / best["unchecked"]}


def main(argv: Optional[list[str]] = None) -> int:
    args = parse_args(argv)
    if args.child:
        return child_main()

    def terminate(signum: int, _frame: Any) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, terminate)
    started = time.monotonic()
    child = ChildSubscriber() if "dds cross-process" in args.modes else None
    rows: list[dict] = []
    try:
        factories = {"image": ImageFactory(), "imu": ImuFactory()}
        sizes = {kind: len(serialize_message(factories[kind].make(0))) for kind in MESSAGES}
        if child is not None:
            child.wait_ready()
        tag = f"{os.getpid()}"
        for kind in args.messages:
            for mode in args.modes:
                rows.extend(run_one(mode, kind, args, child, factories, sizes, tag))
    finally:
        if child is not None:
            child.stop()
    info = {
        "rmw": rclpy.utilities.get_rmw_implementation_identifier(),
        "ros_domain_id": os.environ["ROS_DOMAIN_ID"], "cpus": os.cpu_count(),
        "python": platform.python_version(), "machine": platform.machine(),
        "qos": f"reliable, keep_last {args.depth}, volatile",
        "count": args.count, "small_count": args.small_count, "rate_hz": args.rate, "duration_s": args.duration,
        "wall_s": time.monotonic() - started,
    }
    reuse = reuse_check_cost()
    if args.json:
        print(json.dumps({"info": info, "results": rows, "reuse_check": reuse}, indent=2))
    else:
        print(f"rmw {info['rmw']}, {info['cpus']} CPUs, Python {info['python']}, QoS {info['qos']}; "
              f"burst {args.count} images / {args.small_count} IMU, paced {args.rate:g} Hz for "
              f"{args.duration:g} s; wall {info['wall_s']:.0f} s\n")
        print(markdown_table(rows))
        print(f"\nreuse rule on the zero-copy path (fresh Imu objects, inline subscriber): publish() "
              f"{reuse['publish_ns_with_reuse_check']:.0f} ns with the check, {reuse['publish_ns_without']:.0f} ns "
              f"without: ratio {reuse['ratio']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
