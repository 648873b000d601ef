"""The interface packages built from srv/: composition_interfaces must be the Jazzy types (RIHS01 hashes in
the installed type descriptions, computed from the sources and seen on the wire from a running container),
and rosbag2_interfaces must import and work between two rclpy nodes.
"""
from __future__ import annotations

import importlib
import json
import os
import pathlib
import shutil
import sys
import threading
import time
from typing import Any

import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

import composition_interfaces
from container_process import ContainerClient, ContainerProcess
from ipc_testing.process_context import process_context, process_id

REPO = pathlib.Path(__file__).resolve().parents[1]

# From the reference (composition.md): hashes the Jazzy rosidl wheels give these definitions.
SERVICE_HASHES = {
    "LoadNode": "RIHS01_2e521ef6066fba6d7fc3a3b175d486709f01b4d738d9a59188858546fc8e5acd",
    "UnloadNode": "RIHS01_dce562f83adc735ddcfe9dfb927b89293d4dd0fe2b8fc91e772fb83e970a43b0",
    "ListNodes": "RIHS01_13f30d73a74c844ee4bacf78f3680f08777cad137f10fbd6a648544cc7b59d2a",
}
WIRE_HASHES = {
    "LoadNode_Request": "RIHS01_7d3496175f54f92d652547e144c9b2a3b22afd604f84ed70adfcd1cfe35801b5",
    "LoadNode_Response": "RIHS01_08cdf942efabec2448fd03c131f3627a33ed05376400612425f871feb87ca9fd",
    "UnloadNode_Request": "RIHS01_95d5cfc357956740190c7685ac868d9c7c98dcb8c1416aae8eaa351422074e12",
    "UnloadNode_Response": "RIHS01_fa7fc38f9206220a6bc1558a3c019269e5aa592f7fae01dffbd19f56eb86d599",
    "ListNodes_Request": "RIHS01_57c879a1825b3fa15fd58e70d2e73223af6b9c45c7ae104cc107e73464d3a724",
    "ListNodes_Response": "RIHS01_b7cd8401aedcd85c4cedce384944001d5c1ab611e0164a8207045cfcaf4a2584",
}
# service name on the container -> type name
SERVICES = {"load_node": "LoadNode", "unload_node": "UnloadNode", "list_nodes": "ListNodes"}


def _expected_hashes(service: str) -> dict[str, str]:
    """type name -> hash for the service and its request/response, as the type description lists them."""
    return {
        f"composition_interfaces/srv/{service}": SERVICE_HASHES[service],
        f"composition_interfaces/srv/{service}_Request": WIRE_HASHES[f"{service}_Request"],
        f"composition_interfaces/srv/{service}_Response": WIRE_HASHES[f"{service}_Response"],
    }


def _hashes_in(description_file: pathlib.Path) -> dict[str, str]:
    document = json.loads(description_file.read_text())
    return {entry["type_name"]: entry["hash_string"] for entry in document["type_hashes"]}


def _installed_share_dirs() -> list[pathlib.Path]:
    """Where an install puts share/composition_interfaces: the prefix (wheel install) or, for an editable
    install, the build tree the Python package is imported from (build/interfaces/<distribution>/{python,share})."""
    candidates = [pathlib.Path(sys.prefix) / "share",
                  pathlib.Path(composition_interfaces.__file__).resolve().parents[2] / "share"]
    return [c for c in candidates if (c / "composition_interfaces" / "srv").is_dir()]


def test_a_build_is_reused_only_for_the_same_inputs(tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The interfaces this venv's editable install compiled are reused for a wheel build (what the packaging
    tests do with a clean copy) only while the definitions, the build script and the toolchain are the same."""
    monkeypatch.syspath_prepend(str(REPO / "srv"))  # as setup.py imports it
    script = importlib.import_module("build_interfaces")
    distribution = importlib.import_module("ros_distribution")
    built = REPO / distribution.interfaces_build_dir(distribution.built_for())
    if not (built / script.STAMP).is_file():
        pytest.skip("this venv's interfaces were not built from this tree (no editable install)")
    copy = tmp_path / "interfaces"
    shutil.copytree(built, copy, ignore=shutil.ignore_patterns("work"))
    reused = script.build_all(copy)
    assert not (copy / "work").exists()  # nothing was generated or compiled again
    assert [package.name for package in reused] == script.interface_packages()
    assert all(package.libraries for package in reused)

    srv = shutil.copytree(REPO / "srv", tmp_path / "srv", ignore=shutil.ignore_patterns("__pycache__"))
    unchanged = script.inputs_digest()
    monkeypatch.setattr(script, "SRV_ROOT", srv)
    assert script.inputs_digest() == unchanged
    definition = srv / "composition_interfaces" / "srv" / "ListNodes.srv"
    definition.write_text(definition.read_text() + "\n# a changed definition\n")
    assert script.inputs_digest() != unchanged
    assert script._already_built(copy, script.inputs_digest()) is None  # so build_all compiles again


# --- composition_interfaces: type descriptions and hashes ---------------------------------------------------
@pytest.mark.parametrize("service", sorted(SERVICE_HASHES))
def test_installed_type_description_hashes(service: str) -> None:
    shares = _installed_share_dirs()
    assert shares, "no installed share/composition_interfaces/srv found"
    for share in shares:
        hashes = _hashes_in(share / "composition_interfaces" / "srv" / f"{service}.json")
        for type_name, expected in _expected_hashes(service).items():
            assert hashes.get(type_name) == expected, f"{share}: {type_name}"


def test_hashes_computed_from_the_srv_sources(tmp_path: pathlib.Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """Recompute the hashes from srv/composition_interfaces/*.srv with the rosidl wheels, independently of
    whatever the build left behind."""
    if not os.environ.get("AMENT_PREFIX_PATH"):  # the generators find their templates through it
        monkeypatch.setenv("AMENT_PREFIX_PATH", sys.prefix)
    from rosidl_cli.command.hash.api import generate_type_hashes
    from rosidl_cli.command.translate.api import translate

    include = str(pathlib.Path(sys.prefix) / "share")
    source = REPO / "srv" / "composition_interfaces"
    files = sorted(str(p.relative_to(source)) for p in source.glob("srv/*.srv"))
    assert files == ["srv/ListNodes.srv", "srv/LoadNode.srv", "srv/UnloadNode.srv"]
    idl = translate(package_name="composition_interfaces", interface_files=[f"{source}:{f}" for f in files],
                    output_format="idl", include_paths=[include], output_path=tmp_path / "idl")
    outputs = generate_type_hashes(package_name="composition_interfaces",
                                   interface_files=[str(t) for t in idl], include_paths=[include],
                                   output_path=tmp_path / "hashes")
    computed: dict[str, str] = {}
    for output in outputs:
        computed.update(_hashes_in(pathlib.Path(output)))
    for service in SERVICE_HASHES:
        for type_name, expected in _expected_hashes(service).items():
            assert computed.get(type_name) == expected, type_name


def test_python_types_have_the_jazzy_fields() -> None:
    from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode

    assert LoadNode.Request.get_fields_and_field_types() == {
        "package_name": "string", "plugin_name": "string", "node_name": "string", "node_namespace": "string",
        "log_level": "uint8", "remap_rules": "sequence<string>",
        "parameters": "sequence<rcl_interfaces/Parameter>",
        "extra_arguments": "sequence<rcl_interfaces/Parameter>"}
    assert LoadNode.Response.get_fields_and_field_types() == {
        "success": "boolean", "error_message": "string", "full_node_name": "string", "unique_id": "uint64"}
    assert UnloadNode.Request.get_fields_and_field_types() == {"unique_id": "uint64"}
    assert UnloadNode.Response.get_fields_and_field_types() == {
        "success": "boolean", "error_message": "string"}
    assert ListNodes.Request.get_fields_and_field_types() == {}
    assert ListNodes.Response.get_fields_and_field_types() == {
        "full_node_names": "sequence<string>", "unique_ids": "sequence<uint64>"}


# --- composition_interfaces on the wire ---------------------------------------------------------------------
def _endpoints(get_info: Any, topic: str, pid: int, timeout: float = 10.0) -> list[Any]:
    """The endpoints on ``topic`` of the container node of the process ``pid``, once their node is known (an
    endpoint can be seen before its participant's node names; it is then in no node). A participant's GUID prefix
    holds the low 16 bits of its process id (ipc_testing.process_context.process_id), so another
    container of the same name in the graph (one the test starts, or one a test before it killed, kept until its
    lease ends) is not counted."""
    deadline = time.monotonic() + timeout
    while True:
        found = [i for i in get_info(topic, no_mangle=True)
                 if i.node_name == "ComponentManager" and process_id(i) == pid & 0xFFFF]
        if found or time.monotonic() > deadline:
            return found
        time.sleep(0.05)


def test_wire_type_hashes_of_a_running_container() -> None:
    """Each service of the container under test has one request reader and one reply writer, of the wire types
    and hashes of rclcpp's; a second container of the same name runs beside it (as in a CI run where the graph
    still held a killed one), and its endpoints are not taken for the first one's."""
    node = Node("wire_hash_probe", context=process_context())
    with ContainerProcess(cwd=str(REPO)) as other, ContainerProcess(cwd=str(REPO)) as container:
        try:
            ContainerClient(node).wait()
            assert _endpoints(node.get_subscriptions_info_by_topic, "rq/ComponentManager/_container/load_nodeRequest",
                              other.pid), "the other container is not in the graph"
            for service, type_name in SERVICES.items():
                base = f"ComponentManager/_container/{service}"
                requests = _endpoints(node.get_subscriptions_info_by_topic, f"rq/{base}Request", container.pid)
                replies = _endpoints(node.get_publishers_info_by_topic, f"rr/{base}Reply", container.pid)
                assert len(requests) == 1 and len(replies) == 1, (service, requests, replies)
                assert requests[0].topic_type == f"composition_interfaces::srv::dds_::{type_name}_Request_"
                assert replies[0].topic_type == f"composition_interfaces::srv::dds_::{type_name}_Response_"
                assert str(requests[0].topic_type_hash) == WIRE_HASHES[f"{type_name}_Request"], service
                assert str(replies[0].topic_type_hash) == WIRE_HASHES[f"{type_name}_Response"], service
                assert requests[0].node_namespace == "/" and replies[0].node_namespace == "/"
        finally:
            stopped = container.stop(), other.stop()  # by a signal: neither stays in the graph as a ghost
            node.destroy_node()
            assert stopped == (0, 0), container.output + other.output
    assert not container.alive()


# --- rosbag2_interfaces -------------------------------------------------------------------------------------
class _Pair:
    """Two rclpy nodes (server side, client side) in the process's context, spun on a background thread."""

    def __init__(self) -> None:
        self.context = process_context()
        self.server = Node("rosbag2_interfaces_server", context=self.context)
        self.client = Node("rosbag2_interfaces_client", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.server)
        self.executor.add_node(self.client)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=5.0)
        self.thread.join(timeout=5.0)
        self.server.destroy_node()
        self.client.destroy_node()


@pytest.fixture()
def pair() -> Any:
    p = _Pair()
    yield p
    p.close()


def test_rosbag2_interfaces_definitions() -> None:
    from rosbag2_interfaces.msg import WriteSplitEvent
    from rosbag2_interfaces.srv import IsPaused, Pause, Resume, Snapshot, SplitBagfile, TogglePaused

    for empty in (Pause, Resume, SplitBagfile, TogglePaused):
        assert empty.Request.get_fields_and_field_types() == {}
        assert empty.Response.get_fields_and_field_types() == {}
    assert IsPaused.Request.get_fields_and_field_types() == {}
    assert IsPaused.Response.get_fields_and_field_types() == {"paused": "boolean"}
    assert Snapshot.Request.get_fields_and_field_types() == {}
    assert Snapshot.Response.get_fields_and_field_types() == {"success": "boolean"}
    assert WriteSplitEvent.get_fields_and_field_types() == {
        "closed_file": "string", "opened_file": "string", "node_name": "string"}


@pytest.mark.parametrize("service_name", ["Pause", "Resume", "IsPaused", "TogglePaused", "SplitBagfile",
                                          "Snapshot"])
def test_rosbag2_service_call_between_two_nodes(pair: _Pair, service_name: str) -> None:
    import rosbag2_interfaces.srv

    srv_type = getattr(rosbag2_interfaces.srv, service_name)
    calls: list[Any] = []

    def serve(request: Any, response: Any) -> Any:
        calls.append(request)
        if hasattr(response, "paused"):
            response.paused = True
        if hasattr(response, "success"):
            response.success = True
        return response

    pair.server.create_service(srv_type, f"/rosbag2_recorder/{service_name.lower()}", serve)
    client = pair.client.create_client(srv_type, f"/rosbag2_recorder/{service_name.lower()}")
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(srv_type.Request())
    deadline = time.monotonic() + 10.0
    while not future.done() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert future.done(), f"{service_name}: no reply"
    response = future.result()
    assert isinstance(response, srv_type.Response)
    assert len(calls) == 1
    if service_name == "IsPaused":
        assert response.paused is True
    if service_name == "Snapshot":
        assert response.success is True


def test_rosbag2_write_split_event_between_two_nodes(pair: _Pair) -> None:
    from rosbag2_interfaces.msg import WriteSplitEvent

    received: list[WriteSplitEvent] = []
    subscription = pair.client.create_subscription(WriteSplitEvent, "/events/write_split", received.append, 10)
    publisher = pair.server.create_publisher(WriteSplitEvent, "/events/write_split", 10)
    deadline = time.monotonic() + 20.0
    # matched on both sides: a reliable sample sent before the reader knows the writer can be lost
    while (publisher.get_subscription_count() < 1 or subscription.get_publisher_count() < 1) \
            and time.monotonic() < deadline:
        time.sleep(0.01)
    event = WriteSplitEvent(closed_file="/bags/b_0.mcap", opened_file="/bags/b_1.mcap",
                            node_name="/rosbag2_recorder")
    publisher.publish(event)
    while not received and time.monotonic() < deadline:
        time.sleep(0.01)
    assert received == [event]


# From rosbag2 (Rolling) generated code: the hashes of the loss-event types the recorder publishes.
LOSS_EVENT_HASHES = {
    "rosbag2_interfaces/msg/MessagesLostEvent":
        "RIHS01_b4a1d6322a232c78fbb68976bda0b2313d8083b29259eaf6c63848a4c47ae967",
    "rosbag2_interfaces/msg/MessagesLostEventTopicStat":
        "RIHS01_e46b2b211680a200b625f319b6318596e28f9ed3c5bc241d1b95b26028b917b7",
}


def test_messages_lost_event_types_are_rosbag2_rollings() -> None:
    from rosbag2_interfaces.msg import MessagesLostEvent, MessagesLostEventTopicStat

    assert MessagesLostEvent.get_fields_and_field_types() == {
        "node_name": "string",
        "messages_lost_statistics": "sequence<rosbag2_interfaces/MessagesLostEventTopicStat>"}
    assert MessagesLostEventTopicStat.get_fields_and_field_types() == {
        "topic_name": "string", "messages_lost_in_transport": "uint64", "messages_lost_in_recorder": "uint64"}
    shares = [d for d in _installed_share_dirs() if (d / "rosbag2_interfaces" / "msg").is_dir()]
    assert shares, "no installed share/rosbag2_interfaces/msg found"
    for share in shares:
        for name in ("MessagesLostEvent", "MessagesLostEventTopicStat"):
            hashes = _hashes_in(share / "rosbag2_interfaces" / "msg" / f"{name}.json")
            assert hashes[f"rosbag2_interfaces/msg/{name}"] == LOSS_EVENT_HASHES[f"rosbag2_interfaces/msg/{name}"]
            assert all(hashes[t] == h for t, h in LOSS_EVENT_HASHES.items() if t in hashes)
