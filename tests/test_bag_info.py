"""``ipc-component bag info`` takes what ``ros2 bag info`` takes: a bag directory, one ``.mcap`` or ``.db3`` file,
and names a directory without metadata as an unfinished bag with the repair command. Errors name the path and
the problem, never a raw errno text. Bags are written by rosbags (an independent writer)."""
from __future__ import annotations

import re
from pathlib import Path

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
