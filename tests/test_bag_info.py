"""``ipc-component bag info`` takes what ``ros2 bag info`` takes: a bag directory, one ``.mcap`` or ``.db3`` file,
and names a directory without metadata as an unfinished bag with the repair command. Errors name the path and
the problem, never a raw errno text. Bags are written by rosbags (an independent writer)."""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from ipc_component.cli import main as cli_main

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
T0 = 1_700_000_000_000_000_000
STORAGES = {"mcap": (StoragePlugin.MCAP, ".mcap"), "sqlite3": (StoragePlugin.SQLITE3, ".db3")}


def rosbags_bag(path: Path, storage: str) -> Path:
    """Three /chatter strings 0.5 s apart and one /count, written by rosbags; returns the bag directory."""
    string, int32 = TYPESTORE.types["std_msgs/msg/String"], TYPESTORE.types["std_msgs/msg/Int32"]
    with Writer(path, version=9, storage_plugin=STORAGES[storage][0]) as writer:
        chatter = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=TYPESTORE)
        count = writer.add_connection("/count", "std_msgs/msg/Int32", typestore=TYPESTORE)
        for n in range(3):
            writer.write(chatter, T0 + n * 500_000_000,
                         TYPESTORE.serialize_cdr(string(data=f"m{n}"), "std_msgs/msg/String"))
        writer.write(count, T0 + 250_000_000, TYPESTORE.serialize_cdr(int32(data=7), "std_msgs/msg/Int32"))
    return path


def info(capsys: pytest.CaptureFixture[str], path: Path) -> tuple[int, str, str]:
    code = cli_main(["bag", "info", str(path)])
    out, err = capsys.readouterr()
    return code, out, err


def topic_lines(text: str) -> list[str]:
    return sorted(re.findall(r"Topic: .*", text))


@pytest.mark.parametrize("storage", sorted(STORAGES))
def test_a_single_storage_file_reads_like_its_directory(tmp_path: Path, storage: str,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    bag = rosbags_bag(tmp_path / "bag", storage)
    file = next(bag.glob("*" + STORAGES[storage][1]))
    code_dir, from_dir, _ = info(capsys, bag)
    code_file, from_file, err = info(capsys, file)
    assert (code_dir, code_file) == (0, 0), err
    assert from_file.splitlines()[0] == f"Files:             {file.name}"
    assert f"Storage id:        {storage}" in from_file.splitlines()
    for label in ("Duration:", "Start:", "End:", "Messages:"):
        line = next(line for line in from_file.splitlines() if line.startswith(label))
        assert line in from_dir.splitlines(), (label, from_dir)
    assert "Duration:          1.000000000s" in from_file
    assert "Messages:          4" in from_file
    assert topic_lines(from_file) == topic_lines(from_dir) == [
        "Topic: /chatter | Type: std_msgs/msg/String | Count: 3 | Serialization Format: cdr",
        "Topic: /count | Type: std_msgs/msg/Int32 | Count: 1 | Serialization Format: cdr"]


def test_a_directory_without_metadata_names_the_repair(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = rosbags_bag(tmp_path / "bag", "mcap")
    (bag / "metadata.yaml").unlink()
    code, out, err = info(capsys, bag)
    assert (code, out) == (1, "")
    assert f"'{bag}' is an unfinished bag" in err and f"ipc-component bag recover {bag}" in err


@pytest.mark.parametrize("leftover, named", [("-journal", "rollback journal"), ("-wal", "write-ahead log")])
def test_an_sqlite3_file_a_crash_left_with_its_journal_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                                 leftover: str, named: str) -> None:
    bag = rosbags_bag(tmp_path / "bag", "sqlite3")
    (file,) = bag.glob("*.db3")
    file.with_name(file.name + leftover).write_bytes(b"\0" * 512)
    code, out, err = info(capsys, bag)
    assert code == 0, err
    assert f"Warning: {file.name} is unfinished: a crash left its {named}" in out
    assert f"Run `ipc-component bag recover {bag}`" in out


@pytest.mark.parametrize("case", ["missing", "empty directory", "not a bag file", "under a file"])
def test_errors_name_the_path_and_the_problem(tmp_path: Path, case: str,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    target = {"missing": tmp_path / "nothing", "empty directory": tmp_path / "empty",
              "not a bag file": tmp_path / "notes.mcap", "under a file": tmp_path / "notes.mcap" / "inner"}[case]
    (tmp_path / "empty").mkdir()
    (tmp_path / "notes.mcap").write_text("not a bag\n")
    code, out, err = info(capsys, target)
    assert (code, out) == (1, ""), err
    assert str(target if case != "under a file" else target) in err
    assert "Errno" not in err and "Traceback" not in err
    expected = {"missing": "does not exist", "empty directory": "is not a bag: no metadata.yaml",
                "not a bag file": "notes.mcap", "under a file": "does not exist"}[case]
    assert expected in err, err


# --- --sort, --verbose, --topic-name (rosbag2 Lyrical) --------------------------------------------------------
def event(service: Any, kind: int, client: int, sequence: int) -> bytes:
    """One service event of ``service`` (SetBool or Trigger) as rclpy serializes it, from client ``client``."""
    from rclpy.serialization import serialize_message

    message = service.Event()
    message.info.event_type = kind
    message.info.client_gid = [client] * 16
    message.info.sequence_number = sequence
    if kind < 2:
        message.request = [service.Request()]
    else:
        message.response = [service.Response()]
    return serialize_message(message)


def write_plan(path: Path, types: dict[str, str], plan: list[tuple[str, bytes]], storage: str,
               max_bagfile_size: int) -> dict[str, int]:
    """Write ``plan``'s messages 1 µs apart with this project's writer; returns each topic's bytes."""
    from baglib.format.metadata import TopicInfo
    from baglib.write.writer import BagWriter

    sizes: dict[str, int] = {}
    with BagWriter(path, storage_id=storage, max_bagfile_size=max_bagfile_size) as writer:
        for topic, type_name in types.items():
            writer.add_topic(TopicInfo(topic, type_name))
        for n, (topic, data) in enumerate(plan):
            writer.write(topic, data, T0 + n * 1000, T0 + n * 1000)
            sizes[topic] = sizes.get(topic, 0) + len(data)
    return sizes


def sortable_bag(path: Path, storage: str = "mcap", max_bagfile_size: int = 0) -> dict[str, int]:
    """Three topics and two services whose orders by name, type and count all differ; /set_flag has 10 events
    for 3 calls (two of them by different clients with the same sequence number; the third unanswered) and
    /trigger_me 6 events for 3 calls (server side only): more events, fewer calls. Returns each topic's bytes."""
    from std_msgs.msg import Bool, Int32, String
    from std_srvs.srv import SetBool, Trigger
    from rclpy.serialization import serialize_message

    plan: list[tuple[str, bytes]] = [("/zeta", serialize_message(Bool(data=True)))] * 5
    plan += [("/alpha", serialize_message(String(data="a")))] + [("/mid", serialize_message(Int32(data=3)))] * 3
    for client, sequence, kinds in ((1, 1, range(4)), (1, 2, range(4)), (2, 1, range(2))):
        plan += [("/set_flag/_service_event", event(SetBool, kind, client, sequence)) for kind in kinds]
    for sequence in range(3):
        plan += [("/trigger_me/_service_event", event(Trigger, kind, 1, sequence)) for kind in (1, 2)]
    types = {"/zeta": "std_msgs/msg/Bool", "/alpha": "std_msgs/msg/String", "/mid": "std_msgs/msg/Int32",
             "/set_flag/_service_event": "std_srvs/srv/SetBool_Event",
             "/trigger_me/_service_event": "std_srvs/srv/Trigger_Event"}
    return write_plan(path, types, plan, storage, max_bagfile_size)


def info_lines(capsys: pytest.CaptureFixture[str], *arguments: str) -> list[str]:
    assert cli_main(["bag", "info", *arguments]) == 0
    return capsys.readouterr().out.splitlines()


@pytest.mark.parametrize("sort", ["name", "type", "count", None])
def test_sort_orders_topics_and_services(tmp_path: Path, sort: str | None,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    sortable_bag(tmp_path / "bag")
    lines = info_lines(capsys, str(tmp_path / "bag"), *(["--sort", sort] if sort else []))
    topics = {"/alpha": "Topic: /alpha | Type: std_msgs/msg/String | Count: 1 | Serialization Format: cdr",
              "/mid": "Topic: /mid | Type: std_msgs/msg/Int32 | Count: 3 | Serialization Format: cdr",
              "/zeta": "Topic: /zeta | Type: std_msgs/msg/Bool | Count: 5 | Serialization Format: cdr"}
    services = {"/set_flag": "Service: /set_flag | Type: std_srvs/srv/SetBool | Event Count: 10 | "
                             "Serialization Format: cdr",
                "/trigger_me": "Service: /trigger_me | Type: std_srvs/srv/Trigger | Event Count: 6 | "
                               "Serialization Format: cdr"}
    topic_order = {"name": ["/alpha", "/mid", "/zeta"], "type": ["/zeta", "/mid", "/alpha"],
                   "count": ["/alpha", "/mid", "/zeta"]}[sort or "name"]
    service_order = ["/trigger_me", "/set_flag"] if sort == "count" else ["/set_flag", "/trigger_me"]
    assert lines[7:] == [
        "Messages:          9",
        "Topic information: " + topics[topic_order[0]],
        *("                   " + topics[name] for name in topic_order[1:]),
        "Services:          2",
        "Service information: " + services[service_order[0]],
        "                     " + services[service_order[1]],
        "Actions:           0",
        "Action information:",
    ]


@pytest.mark.parametrize("storage,split", [("mcap", 0), ("sqlite3", 0), ("mcap", 1)])
def test_verbose_counts_requests_and_responses_and_sizes(tmp_path: Path, storage: str, split: int,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """rosbag2's verbose output: a size contribution per topic and service, each service's distinct requests
    and responses (client and sequence number), sorted by their sum with ``--sort count``; in a split bag
    (a file per message), counted over the whole bag."""
    sizes = sortable_bag(tmp_path / "bag", storage, split)
    if split:
        assert len(list((tmp_path / "bag").glob("*.mcap"))) > 10
    plain = info_lines(capsys, str(tmp_path / "bag"))
    lines = info_lines(capsys, str(tmp_path / "bag"), "--verbose", "--sort", "count")
    messages = next(n for n, line in enumerate(lines) if line.startswith("Messages:")) + 1
    assert lines[:messages] == plain[:messages]
    assert lines[messages:] == [
        f"Topic information: Topic: /alpha | Type: std_msgs/msg/String | Count: 1 | "
        f"Size Contribution: {sizes['/alpha']} B | Serialization Format: cdr",
        f"                   Topic: /mid | Type: std_msgs/msg/Int32 | Count: 3 | "
        f"Size Contribution: {sizes['/mid']} B | Serialization Format: cdr",
        f"                   Topic: /zeta | Type: std_msgs/msg/Bool | Count: 5 | "
        f"Size Contribution: {sizes['/zeta']} B | Serialization Format: cdr",
        "Services:          2",
        f"Service information: Service: /set_flag | Type: std_srvs/srv/SetBool | Request Count: 3 | "
        f"Response Count: 2 | Size Contribution: {sizes['/set_flag/_service_event']} B | Serialization Format: cdr",
        f"                     Service: /trigger_me | Type: std_srvs/srv/Trigger | Request Count: 3 | "
        f"Response Count: 3 | Size Contribution: {sizes['/trigger_me/_service_event']} B | "
        f"Serialization Format: cdr",
        "Actions:           0",
        "Action information:",
    ]


def test_topic_names_only_sorted_and_ignored_with_verbose(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    sortable_bag(tmp_path / "bag")
    assert info_lines(capsys, str(tmp_path / "bag"), "-t", "--sort", "type") == ["/zeta", "/mid", "/alpha"]
    lines = info_lines(capsys, str(tmp_path / "bag"), "-t", "-v")
    assert lines[0] == "Warning! You have set both the '-t' and '-v' parameters. The '-t' parameter will be ignored."
    assert lines[1].startswith("Files:") and any("Request Count: 3" in line for line in lines)


def test_an_unknown_sort_is_refused_by_name(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    sortable_bag(tmp_path / "bag")
    with pytest.raises(SystemExit):
        cli_main(["bag", "info", str(tmp_path / "bag"), "--sort", "size"])
    assert "invalid choice: 'size' (choose from 'name', 'type', 'count')" in capsys.readouterr().err


# --- actions (rosbag2 Kilted: rosbag2_py's format_action_with_type and format_action_info) --------------------
FIB_TYPE = "test_msgs/action/Fibonacci"


def action_bag(path: Path, storage: str = "mcap", max_bagfile_size: int = 0) -> dict[str, int]:
    """Two actions and a topic. /fibonacci: 6 send_goal events for 2 calls (the second unanswered), 4 get_result
    events for 1 call, a cancel_goal topic without messages, 3 feedback and 2 status messages (15 messages, 10
    with ``-v``'s requests and responses); /zoo: 12 feedback and 1 status, no service events (13 either way).
    Returns each topic's bytes."""
    from action_msgs.msg import GoalStatusArray
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String
    from test_msgs.action import Fibonacci

    impl = Fibonacci.Impl
    feedback = serialize_message(impl.FeedbackMessage())
    status = serialize_message(GoalStatusArray())
    plan: list[tuple[str, bytes]] = [("/chatter", serialize_message(String(data="x")))]
    plan += [("/fibonacci/_action/send_goal/_service_event", event(impl.SendGoalService, kind, 1, sequence))
             for sequence, kinds in ((1, range(4)), (2, range(2))) for kind in kinds]
    plan += [("/fibonacci/_action/get_result/_service_event", event(impl.GetResultService, kind, 1, 1))
             for kind in range(4)]
    plan += [("/fibonacci/_action/feedback", feedback)] * 3 + [("/fibonacci/_action/status", status)] * 2
    plan += [("/zoo/_action/feedback", feedback)] * 12 + [("/zoo/_action/status", status)]
    types = {"/chatter": "std_msgs/msg/String",
             "/fibonacci/_action/send_goal/_service_event": f"{FIB_TYPE}_SendGoal_Event",
             "/fibonacci/_action/cancel_goal/_service_event": "action_msgs/srv/CancelGoal_Event",
             "/fibonacci/_action/get_result/_service_event": f"{FIB_TYPE}_GetResult_Event",
             "/fibonacci/_action/feedback": f"{FIB_TYPE}_FeedbackMessage",
             "/fibonacci/_action/status": "action_msgs/msg/GoalStatusArray",
             "/zoo/_action/feedback": f"{FIB_TYPE}_FeedbackMessage",
             "/zoo/_action/status": "action_msgs/msg/GoalStatusArray"}
    return write_plan(path, types, plan, storage, max_bagfile_size)


NO_EVENTS = "    Note: no service events (no action introspection where it ran): its goals cannot be replayed"


def test_actions_are_listed_with_each_services_event_count(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """Kilted's layout, every action with its two topics and three services (a missing one counts 0), sorted;
    ``send_goal`` gets its own event count (Kilted prints get_result's there)."""
    action_bag(tmp_path / "bag")
    lines = info_lines(capsys, str(tmp_path / "bag"), "--sort", "count")
    fibonacci = [f"  Action: /fibonacci | Type: {FIB_TYPE} | Topics: 2 | Service: 3 | Serialization Format: cdr",
                 "    Topic: feedback | Count: 3",
                 "    Topic: status | Count: 2",
                 "    Service: send_goal | Event Count: 6",
                 "    Service: cancel_goal | Event Count: 0",
                 "    Service: get_result | Event Count: 4"]
    zoo = [f"  Action: /zoo | Type: {FIB_TYPE} | Topics: 2 | Service: 3 | Serialization Format: cdr",
           "    Topic: feedback | Count: 12",
           "    Topic: status | Count: 1",
           "    Service: send_goal | Event Count: 0",
           "    Service: cancel_goal | Event Count: 0",
           "    Service: get_result | Event Count: 0",
           NO_EVENTS]
    assert lines[7:] == [
        "Messages:          1",  # action messages are not counted, as service events are not
        "Topic information: Topic: /chatter | Type: std_msgs/msg/String | Count: 1 | Serialization Format: cdr",
        "Services:          0",
        "Service information:",
        "Actions:           2",
        "Action information:",
        *zoo, *fibonacci,  # 13 messages before 15
    ]


@pytest.mark.parametrize("storage,split", [("mcap", 0), ("sqlite3", 0), ("mcap", 1)])
def test_verbose_counts_each_actions_requests_and_responses(tmp_path: Path, storage: str, split: int,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """``-v``: per action its size contribution (all its topics) and, per service, the distinct (client, sequence
    number) pairs among request and response events, as Kilted's ``ros2 bag info --verbose``; ``--sort count``
    then orders by requests and responses plus feedback and status (/fibonacci's 10 before /zoo's 13); in a
    split bag (a file per message), counted over the whole bag."""
    sizes = action_bag(tmp_path / "bag", storage, split)
    if split:
        assert len(list((tmp_path / "bag").glob("*.mcap"))) > 10
    lines = info_lines(capsys, str(tmp_path / "bag"), "--verbose", "--sort", "count")
    fib_size = sum(size for topic, size in sizes.items() if topic.startswith("/fibonacci/"))
    zoo_size = sum(size for topic, size in sizes.items() if topic.startswith("/zoo/"))
    assert lines[lines.index("Actions:           2"):] == [
        "Actions:           2",
        "Action information:",
        f"  Action: /fibonacci | Type: {FIB_TYPE} | Topics: 2 | Service: 3 | Size Contribution: {fib_size} B | "
        "Serialization Format: cdr",
        "    Topic: feedback | Count: 3",
        "    Topic: status | Count: 2",
        "    Service: send_goal | Request Count: 2 | Response Count: 1",
        "    Service: cancel_goal | Request Count: 0 | Response Count: 0",
        "    Service: get_result | Request Count: 1 | Response Count: 1",
        f"  Action: /zoo | Type: {FIB_TYPE} | Topics: 2 | Service: 3 | Size Contribution: {zoo_size} B | "
        "Serialization Format: cdr",
        "    Topic: feedback | Count: 12",
        "    Topic: status | Count: 1",
        "    Service: send_goal | Request Count: 0 | Response Count: 0",
        "    Service: cancel_goal | Request Count: 0 | Response Count: 0",
        "    Service: get_result | Request Count: 0 | Response Count: 0",
        NO_EVENTS,
    ]
    assert "Messages:          1" in lines


def test_a_truncated_action_event_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An action's service event too short for its ServiceEventInfo: ``-v`` names the topic and the time."""
    from baglib.format.metadata import TopicInfo
    from baglib.write.writer import BagWriter

    topic = "/fibonacci/_action/send_goal/_service_event"
    with BagWriter(tmp_path / "bag") as writer:
        writer.add_topic(TopicInfo(topic, f"{FIB_TYPE}_SendGoal_Event"))
        writer.write(topic, b"\x00\x01\x00\x00\x01", T0, T0)
    assert cli_main(["bag", "info", "-v", str(tmp_path / "bag")]) == 1
    err = capsys.readouterr().err
    assert f"{topic} at {T0}" in err and "too short for its ServiceEventInfo" in err, err
