"""Reading a bag never writes: the bag verbs on bags that sit on a read-only mount, or in a directory they must
leave as it was.

Every verb that reads a bag runs as users run it (the installed ``ipc-component`` in a process of its own; ``bag
play`` is a container with the player component in it, whose messages a plain rclpy subscription here receives
over Fast DDS) on each bag of :data:`CASES`, once through a read-only bind mount of the bags and once in their
writable directory. Afterwards the bag's directory is the same, byte for byte, with the same names, sizes and
modification times (of the directory too: a file made and removed again shows there), and the temporary
directory the command was given is empty again. ``bag info`` runs once per bag (a verb that reads one bag is one
entry in :data:`VERBS`); ``bag play`` plays every bag in one run, several bags being one timeline of bags each
read as it is read alone.

The SQLite3 cases include a database in WAL mode, as rosbag2's ``resilient`` preset leaves it: a read-only
connection to it would create ``-wal`` and ``-shm`` files next to it, and cannot open it at all where it may
not create them. A database whose write-ahead log or rollback journal still holds changes is refused with the
``bag recover`` hint, on either medium, and left as it is.
"""
from __future__ import annotations

import hashlib
import os
import sqlite3
import stat
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_typestore
from std_msgs.msg import String

from baglib.format.cdr_fast import serialize
from baglib.format.metadata import TopicInfo, qos_profile_dict
from baglib.read.reader import BagReader, BagReadError
from baglib.write.writer import BagWriter
from container_process import read_only_view
from ipc_testing.playback import play_to_the_end
from test_recover import SQLITE_CRASH_CHILD

CLI = str(Path(sys.executable).with_name("ipc-component"))
RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
T0 = 1_700_000_000_000_000_000
COUNT = 30
PERIOD_NS = 10_000_000
SPLIT_EVERY = 10  # the split cases hold three files
RECOVER_HINT = "ipc-component bag recover"


def chatter(n: int) -> bytes:
    return bytes(serialize(String(data=f"message {n}")))


# --- the bags -------------------------------------------------------------------------------------------------
def baglib_bag(path: Path, storage_id: str) -> None:
    """Written by this project's writer, split every :data:`SPLIT_EVERY` messages."""
    with BagWriter(path, storage_id=storage_id) as writer:
        writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String",
                                   offered_qos_profiles=[qos_profile_dict(RELIABLE)]))
        for n in range(COUNT):
            if n and n % SPLIT_EVERY == 0:
                writer.split()
            writer.write("/chatter", chatter(n), T0 + n * PERIOD_NS, T0 + n * PERIOD_NS)


def rosbags_bag(path: Path, storage: str, compression: str = "") -> None:
    """Written by rosbags, an independent writer (rosbag2's FILE zstd compression on request)."""
    writer = Writer(path, version=9, storage_plugin=StoragePlugin[storage])
    if compression:
        writer.set_compression(CompressionMode[compression], CompressionFormat.ZSTD)
    with writer:
        connection = writer.add_connection("/chatter", "std_msgs/msg/String",
                                           typestore=get_typestore(Stores.ROS2_JAZZY))
        for n in range(COUNT):
            writer.write(connection, T0 + n * PERIOD_NS, chatter(n))


def wal_mode_bag(path: Path) -> None:
    """A split SQLite3 bag whose databases are in WAL mode and closed cleanly (no ``-wal`` left): what rosbag2's
    ``resilient`` preset (``PRAGMA journal_mode=WAL``, which the database file keeps) leaves."""
    baglib_bag(path, "sqlite3")
    for database in path.glob("*.db3"):
        db = sqlite3.connect(database)
        assert db.execute("PRAGMA journal_mode=WAL").fetchone() == ("wal",)
        db.close()
        assert database.read_bytes()[18:20] == b"\x02\x02"  # the file format versions of WAL mode
    assert sorted(p.suffix for p in path.iterdir()) == [".db3"] * 3 + [".yaml"]


CASES: dict[str, Callable[[Path], None]] = {
    "baglib-mcap-split": lambda path: baglib_bag(path, "mcap"),
    "baglib-sqlite3-split": lambda path: baglib_bag(path, "sqlite3"),
    "rosbags-mcap": lambda path: rosbags_bag(path, "MCAP"),
    "rosbags-sqlite3": lambda path: rosbags_bag(path, "SQLITE3"),
    "rosbags-sqlite3-zstd-file": lambda path: rosbags_bag(path, "SQLITE3", "FILE"),
    "wal-mode-sqlite3-split": wal_mode_bag,
}
MEDIA = ("read-only mount", "writable directory")


@dataclass(frozen=True)
class Shelf:
    """The bags of :data:`CASES` in ``writable``, and the same directory mounted read-only at ``read_only``
    (``None`` where this process may not mount: ``why_not`` says why)."""

    writable: Path
    read_only: Path | None
    why_not: str

    def bag(self, case: str, medium: str) -> Path:
        if medium == "writable directory":
            return self.writable / case
        if self.read_only is None:
            pytest.skip(f"no read-only bind mount: {self.why_not}")
        return self.read_only / case


@pytest.fixture(scope="module")
def shelf(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Shelf]:
    root = tmp_path_factory.mktemp("read_only")
    writable = root / "bags"
    writable.mkdir()
    for case, write in CASES.items():
        write(writable / case)
    with read_only_view(writable, root / "mounted") as (mounted, why_not):
        yield Shelf(writable, mounted, why_not)


# --- what must not change -------------------------------------------------------------------------------------
def snapshot(root: Path) -> dict[str, tuple[int, int, int, str]]:
    """Every entry under ``root`` (``root`` too): its kind, size, modification time and, for files, the SHA-256 of
    its content."""
    entries = {}
    for path in sorted([root, *root.rglob("*")]):
        status = path.lstat()
        digest = hashlib.sha256(path.read_bytes()).hexdigest() if stat.S_ISREG(status.st_mode) else ""
        entries[str(path.relative_to(root))] = (stat.S_IFMT(status.st_mode), status.st_size, status.st_mtime_ns,
                                                digest)
    return entries


@dataclass(frozen=True)
class Run:
    """One verb on one bag: where the verb reads the bag, a node of this test for subscribers and service clients,
    a writable directory of the test's own (for what a verb writes, such as a merge's output) and the environment
    the command runs with (its ``TMPDIR`` is ``scratch/tmp``)."""

    bag: Path
    node: Node
    scratch: Path
    env: dict[str, str]

    def cli(self, *args: str) -> subprocess.CompletedProcess:
        return subprocess.run([CLI, *args], capture_output=True, text=True, timeout=60, env=self.env)


# --- the verbs --------------------------------------------------------------------------------------------------
def bag_info(run: Run) -> None:
    """``bag info`` on the bag directory (its ``metadata.yaml``) and on each of its storage files (which it
    opens)."""
    result = run.cli("bag", "info", str(run.bag))
    assert result.returncode == 0, result.stderr
    assert f"Messages:          {COUNT}\n" in result.stdout, result.stdout
    counted = 0
    for file in sorted(path for path in run.bag.iterdir() if path.name != "metadata.yaml"):
        result = run.cli("bag", "info", str(file))
        assert result.returncode == 0, result.stderr
        (line,) = [line for line in result.stdout.splitlines() if line.startswith("Messages:")]
        counted += int(line.split()[-1])
    assert counted == COUNT


VERBS: dict[str, Callable[[Run], None]] = {"info": bag_info}


@pytest.mark.parametrize("medium", MEDIA)
@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("verb", VERBS)
def test_reading_leaves_the_bag_as_it_was(verb: str, case: str, medium: str, shelf: Shelf, probe: Node,
                                          tmp_path: Path) -> None:
    bag = shelf.bag(case, medium)
    before = snapshot(shelf.writable / case)
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    VERBS[verb](Run(bag, probe, tmp_path, {**os.environ, "TMPDIR": str(temporary)}))
    assert snapshot(shelf.writable / case) == before
    assert not list(temporary.iterdir()), "the command left temporary files"


@pytest.mark.parametrize("medium", MEDIA)
def test_playing_leaves_every_bag_as_it_was(medium: str, shelf: Shelf, probe: Node, tmp_path: Path) -> None:
    """``bag play`` of every bag of :data:`CASES` at once (several bags play as one timeline: each is read as
    it would be alone), started paused and resumed once this node's subscription has matched the player: every
    message of every bag arrives, in time order, and no bag changed."""
    bags = [shelf.bag(case, medium) for case in CASES]
    before = {case: snapshot(shelf.writable / case) for case in CASES}
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    # equal stamps: bursts of a message per bag, so a subscription deep enough for all of them
    every = QoSProfile(depth=COUNT * len(CASES), reliability=ReliabilityPolicy.RELIABLE)
    got, stdout = play_to_the_end(probe, [CLI, "bag", "play", *bags, "--no-progress"],
                                  env={**os.environ, "TMPDIR": str(temporary)}, qos=every)
    assert got == [f"message {n}" for n in range(COUNT) for _ in CASES], stdout
    assert {case: snapshot(shelf.writable / case) for case in CASES} == before
    assert not list(temporary.iterdir()), "the command left temporary files"


# --- refused, not read wrong ------------------------------------------------------------------------------------
@pytest.fixture()
def pending(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Shelf]:
    """A bag whose database a writer was killed in (``journal``: inside a transaction that had reached the file,
    leaving a hot rollback journal; ``wal``: in WAL mode, after committing rows that only its log holds), with a
    read-only view of it."""
    root = tmp_path / "pending"
    bag = root / "bag"
    root.mkdir()
    baglib_bag(bag, "sqlite3")
    database = next(bag.glob("*.db3"))
    mode = {"journal": "DELETE", "wal": "WAL"}[request.param]
    subprocess.run([sys.executable, "-c", SQLITE_CRASH_CHILD, str(database), mode], check=True, timeout=60)
    side = database.with_name(f"{database.name}-{request.param}")
    assert side.stat().st_size
    with read_only_view(root, tmp_path / "mounted") as (mounted, why_not):
        yield Shelf(root, mounted, why_not)


@pytest.mark.parametrize("medium", MEDIA)
@pytest.mark.parametrize("pending", ["journal", "wal"], indirect=True)
def test_a_database_with_pending_changes_is_refused(pending: Shelf, medium: str) -> None:
    bag = pending.bag("bag", medium)
    before = snapshot(pending.writable / "bag")
    with pytest.raises(BagReadError, match=f"run `{RECOVER_HINT}` on the bag"):
        BagReader(bag)
    assert snapshot(pending.writable / "bag") == before
