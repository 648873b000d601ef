"""``bag recover`` repairs in place: on a disk with no room for a copy, crash-safe when it is itself killed at
any step, and a repair that fails leaves the files as it found them.

Bags are written by the project's writer (what a recorder killed on a full disk leaves), cut as a crash would
cut them, and read back by rosbags and the mcap library; what must survive is taken from the intact original
with the mcap library (every message of a chunk that ends before the cut).
"""
from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader

from baglib.format.metadata import TopicInfo
from baglib.tools.repair import recover_bag
from baglib.write.writer import BagWriter
from container_process import small_filesystem

T0 = 1_718_000_000_000_000_000
MESSAGES = 120
PAYLOAD = 100_000          # bytes of a message: a 12 MB bag in chunks of a few messages each
SEED = int(os.environ.get("IPC_RECOVER_SEED") or random.randrange(2**32))
TOPIC = TopicInfo("/frames", "std_msgs/msg/String")


@pytest.fixture(scope="module", autouse=True)
def announce_seed() -> None:
    print(f"\ntest_recover_in_place seed: {SEED} (IPC_RECOVER_SEED={SEED} replays it)")


def payload(n: int) -> bytes:
    text = f"seq={n:06d} ".encode() + bytes([65 + n % 26]) * (PAYLOAD - 11)
    return b"\x00\x01\x00\x00" + len(text + b"\0").to_bytes(4, "little") + text + b"\0"


@pytest.fixture(scope="module")
def original(tmp_path_factory: pytest.TempPathFactory) -> Path:
    bag = tmp_path_factory.mktemp("original") / "bag"
    with BagWriter(bag) as writer:
        writer.add_topic(TOPIC)
        for n in range(MESSAGES):
            writer.write(TOPIC.name, payload(n), T0 + n * 1_000_000, T0 + n * 1_000_000)
    return bag


def mcap_file(bag: Path) -> Path:
    return next(bag.glob("*.mcap"))


def surviving(bag: Path, cut: int) -> list[bytes]:
    """The messages of the intact bag in chunks that end at or before ``cut`` (mcap library, summary)."""
    with open(mcap_file(bag), "rb") as file:
        reader = make_reader(file)
        ends = [index.chunk_start_offset + index.chunk_length for index in reader.get_summary().chunk_indexes]
        whole = [(index.message_start_time, index.message_end_time) for index, end
                 in zip(reader.get_summary().chunk_indexes, ends) if end <= cut]
        return [message.data for _, _, message in reader.iter_messages()
                if any(start <= message.log_time <= stop for start, stop in whole)]


def crashed_copy(original: Path, destination: Path, cut: int) -> Path:
    """The bag as a recorder killed at ``cut`` bytes leaves it: the file cut there, no metadata.yaml."""
    destination.mkdir(parents=True, exist_ok=True)
    source = mcap_file(original)
    with open(source, "rb") as src, open(destination / source.name, "wb") as dst:
        dst.write(src.read(cut))
    return destination


def read_back(bag: Path) -> list[bytes]:
    """Every message, as rosbags and the mcap library both read it (they must agree)."""
    with Reader(bag) as reader:
        by_rosbags = [bytes(raw) for _, _, raw in reader.messages()]
    with open(mcap_file(bag), "rb") as file:
        by_mcap = [message.data for _, _, message in make_reader(file).iter_messages()]
    assert by_rosbags == by_mcap
    return by_mcap


def free_bytes(directory: Path) -> int:
    stats = os.statvfs(directory)
    return stats.f_bavail * stats.f_frsize


def random_cut(original: Path, rng: random.Random) -> int:
    size = mcap_file(original).stat().st_size
    return rng.randrange(size // 3, size - 64)


def test_a_bag_larger_than_the_free_space_is_recovered_in_place(original: Path, tmp_path: Path) -> None:
    rng = random.Random(SEED)
    cut = random_cut(original, rng)
    with small_filesystem(tmp_path / "disk", 24 * 1024 * 1024) as mounted:
        assert mounted, "needs root to mount a small tmpfs (the tests run as root in CI)"
        bag = crashed_copy(original, tmp_path / "disk" / "bag", cut)
        filler = tmp_path / "disk" / "filler"
        with open(filler, "wb") as file:  # leave 256 KiB: far less than the bag, enough for the journal
            file.write(b"\0" * max(0, free_bytes(filler.parent) - 256 * 1024))
        before = free_bytes(bag)
        assert before < mcap_file(bag).stat().st_size
        report = recover_bag(bag)
        assert report.readable, report.text()
        assert read_back(bag) == surviving(original, cut), f"seed {SEED}, cut {cut}"
        assert free_bytes(bag) >= before - 64 * 1024  # the repair needed at most a few pages
        assert sorted(os.listdir(bag)) == sorted([mcap_file(bag).name, "metadata.yaml"])


#: Runs recover_bag on argv[1] and SIGKILLs itself at the argv[2]-th file-system operation on the bag's files
#: (audit events: open, rename, remove, truncate); prints DONE if it got to the end.
KILLED_AT_STEP = textwrap.dedent("""
    import os, signal, sys
    from baglib.tools.repair import recover_bag
    bag, step = os.path.realpath(sys.argv[1]), int(sys.argv[2])
    seen = 0
    def hook(event, args):
        global seen
        if event in ("open", "os.rename", "os.remove", "os.truncate") and args and \\
                os.path.realpath(str(args[0])).startswith(bag):
            seen += 1
            if seen == step:
                os.kill(os.getpid(), signal.SIGKILL)
    sys.addaudithook(hook)
    report = recover_bag(bag)
    print("DONE", report.readable, seen)
""")


def test_killed_at_every_step_the_next_recover_finishes(original: Path, tmp_path: Path) -> None:
    """Whatever step the kill hits, the next run ends with the very file an uninterrupted repair writes (the
    journal makes the finish exact: re-deriving the patch from a half-patched file would differ)."""
    cut = random_cut(original, random.Random(SEED + 1))
    expected = surviving(original, cut)
    reference = crashed_copy(original, tmp_path / "reference", cut)
    assert recover_bag(reference).readable
    repaired = mcap_file(reference).read_bytes()
    step = 0
    while True:
        step += 1
        bag = crashed_copy(original, tmp_path / f"step{step}", cut)
        run = subprocess.run([sys.executable, "-c", KILLED_AT_STEP, str(bag), str(step)], capture_output=True,
                             text=True, timeout=60)
        finished = run.returncode == 0
        assert finished or run.returncode == -signal.SIGKILL, run.stderr
        report = recover_bag(bag)  # the next run
        assert report.readable, f"seed {SEED}, cut {cut}, killed at step {step}:\n{report.text()}"
        assert read_back(bag) == expected, f"seed {SEED}, cut {cut}, killed at step {step}"
        assert mcap_file(bag).read_bytes() == repaired, f"seed {SEED}, cut {cut}, killed at step {step}"
        assert sorted(os.listdir(bag)) == sorted([mcap_file(bag).name, "metadata.yaml"]), step
        shutil.rmtree(bag)
        if finished:
            assert run.stdout.startswith("DONE True"), run.stdout
            break
    assert step > 5  # the journal, the patch and the metadata each took steps that were interrupted


#: recover_bag under RLIMIT_FSIZE: writing beyond argv[2] bytes fails (EFBIG) as a full disk would.
SIZE_LIMITED = textwrap.dedent("""
    import resource, signal, sys
    from baglib.tools.repair import recover_bag
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    limit = int(sys.argv[2])
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    report = recover_bag(sys.argv[1])
    print(report.text())
    sys.exit(0 if report.readable else 1)
""")


def test_a_repair_that_cannot_grow_the_file_leaves_it_as_found(original: Path, tmp_path: Path) -> None:
    """Cut right after a chunk's message indexes, the repaired file is longer than the damaged one: with no room
    to grow, the patch is undone and every byte is as it was."""
    with open(mcap_file(original), "rb") as file:
        reader = make_reader(file)
        index = reader.get_summary().chunk_indexes[len(reader.get_summary().chunk_indexes) // 2]
    cut = index.chunk_start_offset + index.chunk_length + index.message_index_length
    bag = crashed_copy(original, tmp_path / "bag", cut)
    damaged = mcap_file(bag).read_bytes()
    run = subprocess.run([sys.executable, "-c", SIZE_LIMITED, str(bag), str(cut + 512)], capture_output=True,
                         text=True, timeout=60)
    assert run.returncode == 1, run.stdout + run.stderr
    assert "File too large" in run.stdout, run.stdout
    assert mcap_file(bag).read_bytes() == damaged
    assert sorted(os.listdir(bag)) == [mcap_file(bag).name]
    report = recover_bag(bag)  # with room, the same bag recovers
    assert report.readable, report.text()
    assert read_back(bag) == surviving(original, cut)


#: A writer killed inside a transaction whose pages already reached the database file (hot journal).
KILLED_IN_TRANSACTION = textwrap.dedent("""
    import os, sqlite3, sys
    db = sqlite3.connect(sys.argv[1], isolation_level=None)
    db.execute("PRAGMA journal_mode=DELETE")
    db.execute("PRAGMA cache_size=1")  # spill: the uncommitted transaction reaches the database file
    db.execute("BEGIN")
    db.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (1, ?, ?)",
                   [(n, b"x" * 3000) for n in range(300)])
    os._exit(0)  # as SIGKILL would: no rollback
""")


def test_a_sqlite_bag_with_a_hot_journal_recovers_in_place_on_a_full_disk(tmp_path: Path) -> None:
    with small_filesystem(tmp_path / "disk", 32 * 1024 * 1024) as mounted:
        assert mounted, "needs root to mount a small tmpfs (the tests run as root in CI)"
        bag = tmp_path / "disk" / "bag"
        with BagWriter(bag, "sqlite3") as writer:
            writer.add_topic(TOPIC)
            for n in range(MESSAGES):
                writer.write(TOPIC.name, payload(n), T0 + n * 1_000_000, T0 + n * 1_000_000)
        (bag / "metadata.yaml").unlink()
        database = next(bag.glob("*.db3"))
        subprocess.run([sys.executable, "-c", KILLED_IN_TRANSACTION, str(database)], check=True, timeout=60)
        assert database.with_name(database.name + "-journal").stat().st_size
        with open(tmp_path / "disk" / "filler", "wb") as file:
            file.write(b"\0" * max(0, free_bytes(bag) - 256 * 1024))
        assert free_bytes(bag) < database.stat().st_size  # no room for a copy
        report = recover_bag(bag)
        assert report.readable, report.text()
        assert "rolled back in place" in report.text()
        with Reader(bag) as reader:
            assert [bytes(raw) for _, _, raw in reader.messages()] == [payload(n) for n in range(MESSAGES)]
        assert sorted(os.listdir(bag)) == sorted([database.name, "metadata.yaml"])
