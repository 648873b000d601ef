"""``ipc-component bag play``'s options, parsed by the real command-line parser and turned into the player's
parameters, without a process: the names and values are ros2bag's (Kilted / Lyrical ``ros2bag/verb/play.py``),
the parameters rosbag2's (``config_options_from_node_params.cpp``). Playing itself is tested in test_bag_play.py.
"""
from __future__ import annotations

from typing import Any

import pytest

from ipc_component.bag_play import OPTIONS, player_parameters
from ipc_component.cli import build_parser
from test_cli import verb_paths

T0_NS = 1_700_000_000_123_456_789  # more digits than a double holds exactly


def parameters(*arguments: str) -> dict[str, Any]:
    return player_parameters(build_parser().parse_args(["bag", "play", "bag", *arguments]))


def until(*arguments: str) -> tuple[int, int] | None:
    given = parameters(*arguments)
    if "play.playback_until_timestamp.sec" not in given:
        return None
    return given["play.playback_until_timestamp.sec"], given["play.playback_until_timestamp.nsec"]


def test_playback_until_nsec_is_exact_to_the_nanosecond() -> None:
    assert until("--playback-until-nsec", str(T0_NS)) == (1_700_000_000, 123_456_789)
    assert until("--playback-until-sec", "1700000000.5") == (1_700_000_000, 500_000_000)


@pytest.mark.parametrize("arguments", [[], ["--playback-until-sec", "0"], ["--playback-until-sec", "-1"],
                                       ["--playback-until-nsec", "0"], ["--playback-until-nsec", "-5"]])
def test_zero_or_negative_until_is_no_limit_as_in_ros2bag(arguments: list[str]) -> None:
    """ros2bag's ``get_playback_until_from_arg_group`` takes only a positive value (the player's own parameter
    would read 0 as "publish nothing")."""
    assert until(*arguments) is None


def test_playback_until_sec_and_nsec_are_mutually_exclusive(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        parameters("--playback-until-sec", "1", "--playback-until-nsec", "2")
    assert exit_.value.code == 2
    assert "--playback-until-nsec: not allowed with argument --playback-until-sec" in capsys.readouterr().err


def test_playback_until_nsec_takes_a_whole_number(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parameters("--playback-until-nsec", "1.5")
    assert "--playback-until-nsec: invalid int value: '1.5'" in capsys.readouterr().err


@pytest.mark.parametrize("value, parameter", [("service_introspection", "SERVICE_INTROSPECTION"),
                                              ("client_introspection", "CLIENT_INTROSPECTION")])
def test_service_requests_source_takes_ros2bags_choices(value: str, parameter: str) -> None:
    """ros2bag's choices are lower case; the parameter takes rosbag2's ServiceRequestsSource names."""
    assert parameters("--service-requests-source", value)["play.service_requests_source"] == parameter


def test_service_requests_source_refuses_other_values(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parameters("--service-requests-source", "SERVICE_INTROSPECTION")
    assert "invalid choice: 'SERVICE_INTROSPECTION'" in capsys.readouterr().err


@pytest.mark.parametrize("value, parameter", [("received", "RECEIVED_TIMESTAMP"), ("sent", "SENT_TIMESTAMP")])
def test_message_order_maps_to_rosbag2s_parameter(value: str, parameter: str) -> None:
    assert parameters("--message-order", value)["play.message_order"] == parameter


def test_action_options_map_to_rosbag2s_parameters() -> None:
    given = parameters("--actions", "/fibonacci", "--exclude-actions", "/other", "--send-actions-as-client")
    assert given["play.actions_to_filter"] == ["/fibonacci"]
    assert given["play.exclude_actions_to_filter"] == ["/other"]
    assert given["play.send_actions_as_client"] is True


def test_clock_options_map_to_rosbag2s_parameters_as_ros2bag_does() -> None:
    """``--clock`` also leaves out the bag's own /clock; ``--clock-topics`` / ``--clock-topics-all`` publish it
    at the named topics' messages or at every message."""
    given = parameters("--clock", "--exclude-topics", "/tf")
    assert given["play.clock_publish_frequency"] == 40.0
    assert given["play.exclude_topics_to_filter"] == ["/tf", "/clock"]
    assert given["play.clock_publish_on_topic_publish"] is False
    given = parameters("--clock-topics", "/imu", "/scan")
    assert (given["play.clock_publish_on_topic_publish"], given["play.clock_trigger_topics"]) == (True, ["/imu", "/scan"])
    assert given["play.exclude_topics_to_filter"] == [""]
    given = parameters("--clock-topics-all")
    assert (given["play.clock_publish_on_topic_publish"], given["play.clock_trigger_topics"]) == (True, [""])


@pytest.mark.parametrize("arguments", [["--clock", "10", "--clock-topics", "/imu"],
                                       ["--clock", "--clock-topics-all"],
                                       ["--clock-topics", "/imu", "--clock-topics-all"]])
def test_clock_options_are_mutually_exclusive(arguments: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parameters(*arguments)
    assert "not allowed with argument" in capsys.readouterr().err


def played(*arguments: str) -> dict[str, Any]:
    return player_parameters(build_parser().parse_args(["bag", "play", *arguments]))


@pytest.mark.parametrize(("arguments", "topics"), [
    (["--decode", "my_bag"], [""]),                              # every compressed topic of my_bag
    (["--decode", "/cam/video", "my_bag"], ["/cam/video"]),
    (["my_bag", "--decode"], [""]),
    (["my_bag", "--decode", "/cam/video"], ["/cam/video"]),
    (["-i", "my_bag", "--decode", "/cam/video"], ["/cam/video"]),
])
def test_the_bag_may_follow_decode_as_ros2_bag_play_takes_its_bag_anywhere(arguments: list[str],
                                                                          topics: list[str]) -> None:
    given = played(*arguments)
    assert (given["storage.uri"], given["play.decode"], given["play.decode_topics"]) == ("my_bag", True, topics)


def test_decode_without_a_bag_still_asks_for_one() -> None:
    with pytest.raises(ValueError, match=r"name the bag to play \(bag_path, or -i URI\)"):
        played("--decode")


def test_every_option_a_player_error_is_told_in_is_an_option_of_bag_play_and_sets_that_parameter() -> None:
    """The table that names the player's parameters as the options that set them (ipc_component.bag_play.OPTIONS)
    stays true to the parser and to player_parameters."""
    play = dict(verb_paths(build_parser()))[("bag", "play")]
    flags = {flag for action in play._actions for flag in action.option_strings}
    assert set(OPTIONS.values()) <= flags
    assert set(OPTIONS) <= set(parameters())
