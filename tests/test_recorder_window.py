"""The recorder's window parameters and the container's clock service, against one shared container: bad values
are load errors naming the parameter, the window's run-time parameters refuse bad values with the reason, and
``~/_container/clock`` answers this computer's clock.
"""
from __future__ import annotations

import json
import socket
import time
from typing import Iterator

import pytest
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from container_process import SharedContainer
from ipc_testing import call

NOW = time.time()


@pytest.fixture(scope="module")
def shared_container(ros: None, tmp_path_factory: pytest.TempPathFactory) -> Iterator[SharedContainer]:
    root = tmp_path_factory.mktemp("window_bags")
    container = SharedContainer("--bag-root", str(root), name="window_container")
    yield container
    container.close()


@pytest.mark.parametrize("parameters, error", [
    ({"record.start_at": 5.0}, "parameter 'record.start_at' must be seconds since the epoch"),
    ({"record.stop_at": -1.0}, "parameter 'record.stop_at' must be seconds since the epoch"),
    ({"record.max_duration": -2.0}, "parameter 'record.max_duration' must be 0 (no limit)"),
    ({"record.local_only": True}, "parameter 'record.local_only' records what this container publishes in-process"),
    ({"storage.custom_data": ["no-equals-sign"]}, "entries must be 'key=value', got 'no-equals-sign'"),
])
def test_bad_window_values_are_load_errors(shared: SharedContainer, parameters: dict, error: str) -> None:
    response = shared.client.load("components::Recorder", name="bad_window",
                                  parameters={"storage.uri": "bad", **parameters})
    assert not response.success and error in response.error_message, response.error_message


def test_run_time_window_changes_are_checked(shared: SharedContainer, probe: Node) -> None:
    response = shared.client.load("components::Recorder", name="window",
                                  parameters={"storage.uri": "window", "record.all_topics": True})
    assert response.success, response.error_message
    client = probe.create_client(SetParameters, "/window/set_parameters")
    try:
        def set_values(**values: object) -> list:
            request = SetParameters.Request(parameters=[Parameter(name.replace("__", "."), value=value)
                                                        .to_parameter_msg() for name, value in values.items()])
            return call(probe, client, request, again=True).results

        refused = set_values(record__stop_at=12.5)[0]
        assert not refused.successful and "'record.stop_at' must be seconds since the epoch" in refused.reason
        refused = set_values(storage__custom_data=["x"])[0]
        assert not refused.successful and "'key=value'" in refused.reason
        accepted = set_values(record__stop_at=NOW + 3600, record__split_at=NOW + 1800,
                              storage__custom_data=["site=test"])
        assert all(result.successful for result in accepted), accepted
        stats_client = probe.create_client(Trigger, "/window/get_stats")
        stats = json.loads(call(probe, stats_client, Trigger.Request(), again=True).message)
        probe.destroy_client(stats_client)
        assert stats["window_ns"][1] == round((NOW + 3600) * 1e9) and stats["custom_data"] == {"site": "test"}
    finally:
        probe.destroy_client(client)
        shared.client.unload(response.unique_id)


def test_the_clock_service_answers_time_host_and_bag_root(shared: SharedContainer, probe: Node) -> None:
    client = probe.create_client(Trigger, f"{shared.process.name}/_container/clock")
    try:
        before = time.time_ns()
        facts = json.loads(call(probe, client, Trigger.Request(), again=True).message)
        after = time.time_ns()
    finally:
        probe.destroy_client(client)
    assert before <= facts["time_ns"] <= after  # one machine, one clock
    assert facts["host"] == socket.gethostname() and facts["bag_root"].endswith("window_bags0")
