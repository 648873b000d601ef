"""Recorded bytes are the bytes a raw DDS subscription receives, for every installed message type.

The recorder serializes in-process messages itself (``cdr_fast.serialize``); a bag is only right if those
bytes are the ones the middleware would have delivered, because independent readers check the length
(rosbags rejects "CDR message size mismatch"). So every message type of every interface package in the
environment (discovered, not listed: the ROS wheels' packages and this repo's srv/ packages, their
messages and their services' Request, Response and Event messages) is published by a plain rclpy
publisher, default-filled and randomly filled, and received by a raw subscription in this process.
Per message:

* ``cdr_fast.serialize(msg)`` equals the received sample byte for byte;
* ``cdr_size.serialized_size(msg)`` equals its length;
* rosbags' Jazzy typestore decodes it, and re-encodes the decoded message to the same bytes.

rclpy's own bytes can be longer (its length is rmw_fastrtps' size estimate) and hold heap garbage in the
alignment padding; the last test makes both happen on purpose and still expects the sample.

The random corpus comes from a seeded generator: the seed is in every failure message, and
``WIRE_EXACT_SEED=<seed>`` reproduces a run.
"""
from __future__ import annotations

import importlib
import importlib.util
import os
import pkgutil
import random
import struct
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy
from rcl_interfaces.msg import ParameterEvent
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosbags.typesys import Stores, get_typestore
from rosidl_parser import definition
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from visualization_msgs.msg import Marker, MarkerArray

from baglib.format import cdr_fast
from baglib.format.cdr_fast import MIN_BUFFERS_SIZE, serialize
from baglib.format.cdr_size import serialized_layout, serialized_size
from ipc_testing.process_context import process_context

SEED = int(os.environ.get("WIRE_EXACT_SEED") or random.randrange(2**32))
RANDOM_MESSAGES = 4
#: Lengths drawn for sequences (cut to their bound): empty ones matter as much as long ones.
SEQUENCE_LENGTHS = (0, 0, 1, 2, 3)
PRIMITIVE_SEQUENCE_LENGTHS = (0, 1, 2, 3, 5, 17, 100)
#: Characters of random strings: ASCII, 2-, 3- and 4-byte UTF-8 (a UTF-16 surrogate pair), and NUL.
ALPHABET = "az_/09 éü߷相机😀\x00"
#: How long to wait for discovery and delivery before the test fails (a guard against hanging, not a
#: claim about speed: on a loaded machine both take well under a second).
PATIENCE_S = 60.0
#: KEEP_ALL also keeps every sample in the writer's history, so Fast DDS serializes each one into a fresh
#: (zeroed) buffer: a reused buffer would carry stale bytes in the padding, which no serializer can match.
QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                 durability=DurabilityPolicy.VOLATILE)
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
REPO = Path(__file__).resolve().parents[1]
#: Interface packages of the test extras, not of what the product runs with (test_msgs: the action tests' Fibonacci).
TEST_ONLY_PACKAGES = {"test_msgs"}


# --- what is installed -------------------------------------------------------------------------------


def interface_packages() -> list[str]:
    """Importable packages with rosidl typesupport: top-level modules plus this repo's srv/ packages.

    The installed packages are looked at where ``pkgutil`` found them, without ``find_spec``: setuptools'
    distutils hook answers ``find_spec("pip")`` by unloading distutils, with a warning. The srv/ packages are
    listed by folder, and found with ``find_spec``, because an editable install serves them through an import
    hook that ``pkgutil`` does not enumerate.
    """
    def has_typesupport(name: str, folders: Iterable[str]) -> bool:
        return any(any(Path(folder).glob(f"{name}_s__rosidl_typesupport_c*")) for folder in folders)

    packages = {module.name for module in pkgutil.iter_modules()
                if module.ispkg and module.name not in TEST_ONLY_PACKAGES
                and has_typesupport(module.name, [os.path.join(getattr(module.module_finder, "path", ""),
                                                               module.name)])}
    for folder in (REPO / "srv").iterdir():
        spec = importlib.util.find_spec(folder.name) if folder.is_dir() else None
        if spec and has_typesupport(folder.name, spec.submodule_search_locations or []):
            packages.add(folder.name)
    return sorted(packages)


def message_classes() -> list[type]:
    """Every message class of the interface packages: msg, and srv/action Request, Response, Event..."""
    classes = []
    for package in interface_packages():
        for kind in ("msg", "srv", "action"):
            try:
                module = importlib.import_module(f"{package}.{kind}")
            except ModuleNotFoundError:
                continue
            classes += [value for _, value in sorted(vars(module).items())
                        if isinstance(value, type) and hasattr(value, "SLOT_TYPES")]
    return classes


def type_name(cls: type) -> str:
    """``pkg/msg/Name`` (``pkg/srv/Name_Request``...), as rosbag2 and rosbags name types."""
    package, kind = cls.__module__.split(".")[:2]
    return f"{package}/{kind}/{cls.__name__}"


MESSAGE_CLASSES = message_classes()


# --- a seeded random corpus --------------------------------------------------------------------------

_INTEGER_BITS = {"uint8": (False, 8), "int8": (True, 8), "uint16": (False, 16), "int16": (True, 16),
                 "uint32": (False, 32), "int32": (True, 32), "uint64": (False, 64), "int64": (True, 64)}


def _primitive(typename: str, rng: random.Random) -> Any:
    if typename == "boolean":
        return rng.random() < 0.5
    if typename == "octet":
        return bytes([rng.randrange(256)])
    if typename in ("float", "double"):
        value = rng.uniform(-1e6, 1e6)
        return struct.unpack("<f", struct.pack("<f", value))[0] if typename == "float" else value
    signed, bits = _INTEGER_BITS[typename]
    low = -(1 << (bits - 1)) if signed else 0
    return rng.randrange(low, low + (1 << bits))


def _text(rng: random.Random, bound: int | None, units: str) -> str:
    """Random text of at most ``bound`` characters and ``bound`` code units of ``units`` (the wire's)."""
    limit = rng.choice((0, 1, 2, 5, 12, 40))
    limit = limit if bound is None else min(limit, bound)
    text = ""
    for _ in range(limit):
        candidate = text + rng.choice(ALPHABET)
        if bound is not None and len(candidate.encode(units)) // (2 if units == "utf-16-le" else 1) > bound:
            break
        text = candidate
    return text


def _length(rng: random.Random, slot: definition.AbstractSequence) -> int:
    element_is_primitive = isinstance(slot.value_type, definition.BasicType)
    length = rng.choice(PRIMITIVE_SEQUENCE_LENGTHS if element_is_primitive else SEQUENCE_LENGTHS)
    return min(length, slot.maximum_size) if isinstance(slot, definition.BoundedSequence) else length


def random_value(slot: definition.AbstractType, rng: random.Random) -> Any:
    """A random value of a field's rosidl type, within its bounds."""
    if isinstance(slot, definition.BasicType):
        return _primitive(slot.typename, rng)
    if isinstance(slot, definition.AbstractGenericString):
        bound = slot.maximum_size if slot.has_maximum_size() else None
        return _text(rng, bound, "utf-16-le" if isinstance(slot, definition.AbstractWString) else "utf-8")
    if isinstance(slot, definition.NamespacedType):
        module = importlib.import_module(".".join(slot.namespaces))
        return random_message(getattr(module, slot.name), rng)
    if isinstance(slot, definition.Array):
        return [random_value(slot.value_type, rng) for _ in range(slot.size)]
    if isinstance(slot, definition.AbstractSequence):
        return [random_value(slot.value_type, rng) for _ in range(_length(rng, slot))]
    raise TypeError(f"no random values for {slot!r}")


def random_message(cls: type, rng: random.Random) -> Any:
    msg = cls()
    for name, slot in zip(cls.get_fields_and_field_types(), cls.SLOT_TYPES, strict=True):
        setattr(msg, name, random_value(slot, rng))
    return msg


def corpus(cls: type, rng: random.Random) -> list[Any]:
    return [cls(), *(random_message(cls, rng) for _ in range(RANDOM_MESSAGES))]


def big_messages(rng: random.Random) -> list[Any]:
    """Fallback messages past MIN_BUFFERS_SIZE, which ``serialize`` cuts as views."""
    array = Float64MultiArray(data=[rng.random() for _ in range(20_000)])
    array.layout.dim = [MultiArrayDimension(label="odd", size=20_000, stride=1)]  # padding before the data
    markers = MarkerArray(markers=[random_message(Marker, rng) for _ in range(300)])  # >= 300 * 229 bytes
    return [array, markers]


# --- the wire ------------------------------------------------------------------------------------------


class WireProbe:
    """A publisher and a raw subscription per type, matched before anything is published."""

    def __init__(self, node: Node, cls: type, index: int) -> None:
        self.samples: list[bytes] = []
        self.publisher_matches = self.subscription_matches = 0
        topic = f"/wire_exact/t{index}"
        self.subscription = node.create_subscription(
            cls, topic, self.samples.append, QOS, raw=True,
            event_callbacks=SubscriptionEventCallbacks(matched=self._subscription_matched))
        self.publisher = node.create_publisher(
            cls, topic, QOS, event_callbacks=PublisherEventCallbacks(matched=self._publisher_matched))

    def _subscription_matched(self, status: Any) -> None:
        self.subscription_matches = status.current_count

    def _publisher_matched(self, status: Any) -> None:
        self.publisher_matches = status.current_count

    def is_matched(self) -> bool:
        return self.publisher_matches > 0 and self.subscription_matches > 0

    def destroy(self, node: Node) -> None:
        node.destroy_publisher(self.publisher)
        node.destroy_subscription(self.subscription)


def spin_until(executor: SingleThreadedExecutor, condition: Callable[[], bool]) -> bool:
    deadline = time.monotonic() + PATIENCE_S
    while not condition() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return condition()


@pytest.fixture(scope="module")
def wire() -> Iterator[dict[type, list[tuple[Any, bytes]]]]:
    """Every type's corpus with the samples a raw subscription received for it, in publishing order."""
    rng = random.Random(SEED)
    print(f"wire-exact corpus seed {SEED} (WIRE_EXACT_SEED={SEED} reproduces it)")
    messages = {cls: corpus(cls, rng) for cls in MESSAGE_CLASSES}
    for msg in big_messages(rng):
        messages[type(msg)].append(msg)
    context = process_context()
    node = rclpy.create_node("wire_exact", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        probes = {cls: WireProbe(node, cls, index) for index, cls in enumerate(MESSAGE_CLASSES)}
        assert spin_until(executor, lambda: all(p.is_matched() for p in probes.values())), \
            [type_name(cls) for cls, probe in probes.items() if not probe.is_matched()]
        for cls, probe in probes.items():
            for msg in messages[cls]:
                probe.publisher.publish(msg)
        assert spin_until(executor, lambda: all(len(probes[cls].samples) == len(messages[cls]) for cls in probes))
        yield {cls: list(zip(messages[cls], probes[cls].samples, strict=True)) for cls in MESSAGE_CLASSES}
        for probe in probes.values():
            probe.destroy(node)
    finally:
        executor.shutdown()
        node.destroy_node()


def test_every_interface_package_is_covered() -> None:
    """The discovery finds the wheels' packages and this repo's, so no type is silently left out."""
    packages = interface_packages()
    assert {"std_msgs", "sensor_msgs", "rcl_interfaces", "std_srvs", "composition_interfaces",
            "rosbag2_interfaces"} <= set(packages)
    names = {type_name(cls) for cls in MESSAGE_CLASSES}
    assert {"rcl_interfaces/msg/ParameterEvent", "std_msgs/msg/Empty", "std_srvs/srv/SetBool_Request",
            "std_srvs/srv/SetBool_Event", "rosbag2_interfaces/msg/WriteSplitEvent"} <= names


def test_recorded_bytes_are_the_wire_bytes(wire: dict[type, list[tuple[Any, bytes]]]) -> None:
    wrong = []
    for cls in MESSAGE_CLASSES:
        for n, (msg, sample) in enumerate(wire[cls]):
            if bytes(serialize(msg)) != sample or serialized_size(msg) != len(sample):
                wrong.append(f"{type_name(cls)} message {n}")
    assert not wrong, f"seed {SEED}: {len(wrong)} messages not as on the wire: {wrong[:50]}"


def test_rosbags_reads_the_recorded_bytes(wire: dict[type, list[tuple[Any, bytes]]]) -> None:
    """Every type that rosbags' Jazzy typestore knows decodes and re-encodes to the recorded bytes."""
    known = [cls for cls in MESSAGE_CLASSES if type_name(cls) in TYPESTORE.fielddefs]
    assert len(known) > len(MESSAGE_CLASSES) // 2
    wrong = []
    for cls in known:
        name = type_name(cls)
        for n, (msg, _) in enumerate(wire[cls]):
            recorded = bytes(serialize(msg))
            try:
                again = bytes(TYPESTORE.serialize_cdr(TYPESTORE.deserialize_cdr(recorded, name), name))
            except Exception as error:  # noqa: BLE001 - listed with the others
                wrong.append(f"{name} message {n}: {error!r}")
                continue
            if again != recorded:
                wrong.append(f"{name} message {n}")
    assert not wrong, f"seed {SEED}: {len(wrong)} messages rosbags reads otherwise: {wrong[:50]}"


def test_what_rclpy_leaves_is_cut_and_cleaned(wire: dict[type, list[tuple[Any, bytes]]],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Stale padding and a size estimate past the end, as rclpy may return them, still give the sample.

    Whether rclpy's padding is dirty depends on the heap, so it is made dirty here, for small messages
    and for the big ones that come back as views.
    """
    def dirty(msg: Any) -> bytes:
        data = bytearray(serialize_message(msg))
        for start, stop in serialized_layout(msg).padding:
            data[start:stop] = b"\xa5" * (stop - start)
        return bytes(data) + bytes(8)

    monkeypatch.setattr(cdr_fast, "serialize_message", dirty)
    views = set()
    for cls in (ParameterEvent, Float64MultiArray, MarkerArray):
        for n, (msg, sample) in enumerate(wire[cls]):
            result = serialize(msg)
            assert bytes(result) == sample, f"{type_name(cls)} message {n} of seed {SEED}"
            assert isinstance(result, memoryview if len(sample) >= MIN_BUFFERS_SIZE else bytes)
            if isinstance(result, memoryview):
                views.add(cls)
    assert views == {Float64MultiArray, MarkerArray}  # the big messages of the corpus
