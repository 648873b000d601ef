"""Power cuts, explored: crash states of real recordings under an ext4 ``data=ordered`` model.

The recorder's crash tests (test_crash_recovery, test_loss_bounds) SIGKILL it, which loses nothing the process had
handed to the kernel. A power cut also loses what the page cache and the disk's cache had not made durable. These
tests trace the real file-system operations (strace) and build the states a power cut can leave
(tests/crash_states, docs/design/power-cut.md):

* the model itself, on a small traced script whose crash states are known;
* the bag writer alone: once ``BagWriter.sync()`` has returned, every crash state holds every message;
* ``bag recover`` sets aside a file it leaves out, so that ``bag info`` has nothing left to warn about;
* a real container recording (camera, IMU, recorders for MCAP and SQLite3, split and unsplit) captured once per
  test run, and a seeded subset of its crash states recovered and checked (the sweep, ``python
  tests/crash_states/sweep.py``, tries thousands). ``IPC_POWER_CUT_SEED`` moves the seeds; every failing seed is
  printed with the state it drew.
"""
from __future__ import annotations

import fcntl
import io
import os
import random
import sqlite3
import textwrap
from pathlib import Path

import pytest
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from crash_states.capture import CONFIGS, trace_script, strace_usable
from crash_states.model import BagModel
from crash_states.strace_log import parse_trace
from crash_states.sweep import explore, load_capture, prepare

from baglib.format.metadata import TopicInfo
from baglib.tools.info import format_bag_info
from baglib.tools.repair import recover_bag
from baglib.write.writer import BagWriter

UNUSABLE = strace_usable()
needs_strace = pytest.mark.skipif(UNUSABLE is not None, reason=UNUSABLE or "")

#: Crash states per configuration in the default run (the sweep runs 1000 and more).
STATES = int(os.environ.get("IPC_POWER_CUT_STATES") or 50)
SEED = int(os.environ.get("IPC_POWER_CUT_SEED") or 0)


def _root(tmp_path: Path) -> Path:
    root = tmp_path / "root"
    root.mkdir()
    fd = os.open(root, os.O_RDONLY)
    os.fsync(fd)
    os.close(fd)
    return root


MODEL_SCRIPT = textwrap.dedent("""
    import os, sys
    d = os.path.join(sys.argv[1], "d")
    os.mkdir(d)
    fd = os.open(sys.argv[1], os.O_RDONLY); os.fsync(fd); os.close(fd)        # d's name is durable
    a = os.open(d + "/a", os.O_WRONLY | os.O_CREAT, 0o644)
    os.write(a, b"A" * 8192); os.fsync(a)                                        # durable: 8192 x A
    os.write(a, b"B" * 8192)                                                     # appended, not synced
    os.pwrite(a, b"C" * 4096, 0)                                                 # overwrites a durable block
    t = os.open(d + "/t.tmp", os.O_WRONLY | os.O_CREAT, 0o644)
    os.write(t, b"T" * 100); os.fsync(t); os.close(t)
    os.rename(d + "/t.tmp", d + "/t")
    fd = os.open(d, os.O_RDONLY); os.fsync(fd); os.close(fd)                     # a, t: names durable
    os.write(a, b"E" * 100)                                                      # appended, not synced
    u = os.open(d + "/u", os.O_WRONLY | os.O_CREAT, 0o644); os.write(u, b"U" * 5000)  # never synced
    os.unlink(d + "/t")                                                          # not synced
""")


@needs_strace
def test_the_model_keeps_what_was_made_durable_and_varies_the_rest(tmp_path: Path) -> None:
    root = _root(tmp_path)
    trace = parse_trace(trace_script(tmp_path, MODEL_SCRIPT, str(root)), root, tmp_path)
    model = BagModel(trace, "d", "strict")
    end = model.last_line + 1
    killed = model.sigkill_state(end)
    assert killed.files == {"a": b"C" * 4096 + b"A" * 4096 + b"B" * 8192 + b"E" * 100, "u": b"U" * 5000}
    seen: dict[str, set] = {"head": set(), "size": set(), "t": set(), "u": set()}
    for seed in range(400):
        state = model.draw(random.Random(seed), cut=end)
        assert state.bag_exists, state.describe()
        a = state.files["a"]
        assert a[4096:8192] == b"A" * 4096 and a[:4096] in (b"A" * 4096, b"C" * 4096), state.describe()
        assert len(a) in (8192, 16384, 16484), state.describe()
        if len(a) >= 16384:  # data=ordered: the appended size persisted, so did the data under it
            assert a[8192:16384] == b"B" * 8192, state.describe()
        if len(a) == 16484:
            assert a[16384:] == b"E" * 100, state.describe()
        assert "t.tmp" not in state.files and state.files.get("t", b"T" * 100) == b"T" * 100, state.describe()
        assert state.files.get("u", b"") in (b"", b"U" * 5000), state.describe()
        seen["head"].add(a[:1])
        seen["size"].add(len(a))
        seen["t"].add("t" in state.files)
        seen["u"].add(state.files.get("u"))
    # every freedom of the model shows up
    assert seen == {"head": {b"A", b"C"}, "size": {8192, 16384, 16484}, "t": {True, False},
                    "u": {None, b"", b"U" * 5000}}
    # before the directory's fsync, u's and a's names may be gone; d's never (its parent was fsynced)
    directory_sync = next(op for op in model.ops if op.kind == "fsync" and op.ino == model.bag_ino)
    early = [model.draw(random.Random(seed), cut=directory_sync.seq_in) for seed in range(100)]
    assert all(state.bag_exists for state in early)
    assert {"a" in state.files for state in early} == {True, False}


WRITER_SCRIPT = textwrap.dedent("""
    import os, sys
    from pathlib import Path
    from baglib.format.metadata import TopicInfo
    from baglib.write.writer import BagWriter
    writer = BagWriter(Path(sys.argv[1]), storage_id=sys.argv[2])
    writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String"))
    for i in range(300):
        text = b"message %04d" % i + bytes(1)
        writer.write("/chatter", bytes(4) + len(text).to_bytes(4, "little") + text, 10**9 + i, 10**9 + i)
    writer.sync()
    writer._syncing.join()
    os._exit(0)  # the power fails right after the sync: nothing was finalized
""")


def _chatter(state, storage: str, scratch: Path) -> list[bytes]:
    """The /chatter payloads a crash state holds (complete MCAP records; committed SQLite rows)."""
    found: list[bytes] = []
    for name, content in sorted(state.files.items()):
        if storage == "mcap" and name.endswith(".mcap"):
            channels = {}
            try:
                for record in StreamReader(io.BytesIO(content), skip_magic=False).records:
                    if isinstance(record, Channel):
                        channels[record.id] = record.topic
                    elif isinstance(record, Message) and channels.get(record.channel_id) == "/chatter":
                        found.append(bytes(record.data))
            except Exception:  # noqa: BLE001 - the unfinished end of the file
                pass
    if storage == "sqlite3":
        bag = state.materialize(scratch)
        for path in sorted(bag.glob("*.db3")) if bag else []:
            with sqlite3.connect(path) as db:
                found += [bytes(data) for (data,) in db.execute("SELECT data FROM messages ORDER BY id")]
    return found


@needs_strace
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_every_crash_state_after_a_sync_holds_every_message(tmp_path: Path, storage: str) -> None:
    """Once ``sync()`` has fsynced the file (on its thread), a power cut keeps the bag directory, the file's name
    and every message: the bag's parent and directory are fsynced too (and, for SQLite3, the removal of the last
    commit's rollback journal with it: a journal that came back would roll that transaction back)."""
    root = _root(tmp_path)
    trace = parse_trace(trace_script(tmp_path, WRITER_SCRIPT, str(root / "bag"), storage), root, tmp_path)
    model = BagModel(trace, "bag", "strict")
    expected = _chatter(model.sigkill_state(model.last_line + 1), storage, tmp_path / "killed")
    assert len(expected) == 300
    for seed in range(200):
        state = model.draw(random.Random(seed), cut=model.last_line + 1)
        scratch = tmp_path / f"state{seed}"
        assert _chatter(state, storage, scratch) == expected, f"seed {seed}:\n{state.describe()}"


FULL_DISK_SCRIPT = textwrap.dedent("""
    import os, resource, signal, sys
    from pathlib import Path
    from baglib.format.metadata import TopicInfo
    from baglib.write.writer import BagWriteError, BagWriter
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))  # the disk fills at 64 KiB
    writer = BagWriter(Path(sys.argv[1]))
    writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String"))
    try:
        for i in range(10_000):
            text = b"message %04d" % i + bytes(200)
            writer.write("/chatter", bytes(4) + len(text).to_bytes(4, "little") + text, 10**9 + i, 10**9 + i)
    except BagWriteError:
        pass
    try:
        writer.close()  # the file was repaired (cut after its last record, summary appended); metadata.yaml
    except BagWriteError:
        pass
    os._exit(0)
""")


@needs_strace
def test_a_file_repaired_after_a_full_disk_is_durable_before_metadata_names_it(tmp_path: Path) -> None:
    """When a write fails (a full disk), the MCAP storage repairs its file and the writer then lists it in
    ``metadata.yaml``. Every crash state in which that ``metadata.yaml`` exists must hold the file as repaired:
    readable, with the messages ``metadata.yaml`` counts."""
    import yaml
    from mcap.reader import make_reader

    root = _root(tmp_path)
    trace = parse_trace(trace_script(tmp_path, FULL_DISK_SCRIPT, str(root / "bag")), root, tmp_path)
    model = BagModel(trace, "bag", "strict")
    checked = 0
    for seed in range(200):
        state = model.draw(random.Random(seed), cut=model.last_line + 1)
        if "metadata.yaml" not in state.files:
            continue
        checked += 1
        listed = yaml.safe_load(state.files["metadata.yaml"])["rosbag2_bagfile_information"]["files"]
        for entry in listed:
            content = state.files.get(entry["path"])
            assert content is not None, f"seed {seed}: metadata.yaml names a missing file\n{state.describe()}"
            try:
                summary = make_reader(io.BytesIO(content)).get_summary()
            except Exception as exc:  # noqa: BLE001 - any unreadable file is the failure
                raise AssertionError(f"seed {seed}: {entry['path']} unreadable ({exc})\n{state.describe()}") from None
            assert summary is not None and summary.statistics.message_count == entry["message_count"], (
                f"seed {seed}\n{state.describe()}")
    assert checked > 50, "metadata.yaml was (almost) never durable: the script did not finish as intended"


RECOVER_SCRIPT = textwrap.dedent("""
    import os, sys
    from pathlib import Path
    from baglib.format.metadata import TopicInfo
    from baglib.tools.repair import recover_bag
    from baglib.write.writer import BagWriter
    bag = Path(sys.argv[1])
    writer = BagWriter(bag, storage_id=sys.argv[2])
    writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String"))
    for i in range(300):
        text = b"message %04d" % i + bytes(1)
        writer.write("/chatter", bytes(4) + len(text).to_bytes(4, "little") + text, 10**9 + i, 10**9 + i)
    writer.sync()
    writer._syncing.join()  # the recorder crashed here: every message durable, the bag never finalized
    if sys.argv[2] == "sqlite3" and os.fork() == 0:  # and in the middle of a transaction: a hot journal
        import sqlite3
        db = sqlite3.connect(next(bag.glob("*.db3")), isolation_level=None)
        db.execute("PRAGMA cache_size=1")  # pages spill to the file: the journal holds their old content
        db.execute("BEGIN")
        for i in range(200):
            db.execute("INSERT INTO messages (topic_id, timestamp, data) VALUES (1, ?, ?)", (i, bytes(2000)))
        os._exit(0)
    if sys.argv[2] == "sqlite3":
        os.wait()
        assert next(bag.glob("*.db3-journal"))
    (bag.parent / "recover-starts").touch()  # marks the line where the recover begins
    report = recover_bag(bag)
    assert report.readable, report.text()
    os._exit(0)
""")


@needs_strace
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_a_power_cut_during_recover_in_place_loses_nothing_the_next_recover_finds(tmp_path: Path,
                                                                               storage: str) -> None:
    """``bag recover`` repairs in place (a journal of its patches, SQLite's own rollback journal). A power cut at
    any moment of it, in any state the model allows, must leave a bag that the next ``bag recover`` makes whole:
    every message that was durable before the recover began, nothing twice."""
    from baglib.read.reader import BagReader

    root = _root(tmp_path)
    trace = parse_trace(trace_script(tmp_path, RECOVER_SCRIPT, str(root / "bag"), storage), root, tmp_path)
    marker = next(op for op in trace.ops if op.path == "recover-starts")
    model = BagModel(trace, "bag", "strict")
    cuts = sorted({line for op in model.ops if op.seq_in > marker.seq_out
                   for line in (op.seq_in, op.seq_out + 1)} | {model.last_line + 1})
    assert len(cuts) >= 5, f"the recover did (almost) nothing on disk: {len(cuts)} cut positions"
    rng = random.Random(SEED)
    print(f"IPC_POWER_CUT_SEED={SEED}: 150 states over {len(cuts)} cut positions of the recover ({storage})")
    for n in range(150):
        state = model.draw(rng, cut=rng.choice(cuts))
        bag = state.materialize(tmp_path / f"state{n}")
        assert bag is not None, f"state {n}: the bag directory is gone\n{state.describe()}"
        report = recover_bag(bag)
        assert report.readable, f"state {n}: {report.text()}\n{state.describe()}"
        with BagReader(bag) as reader:
            payloads = [bytes(message.data) for message in reader.messages()]
        assert payloads == [bytes(4) + (13).to_bytes(4, "little") + b"message %04d" % i + bytes(1)
                            for i in range(300)], f"state {n}: {len(payloads)} messages\n{state.describe()}"


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_recover_sets_aside_a_file_it_leaves_out(tmp_path: Path, storage: str) -> None:
    """A split file prepared just before a crash may hold nothing (its header was still in the writer's buffer):
    recover leaves it out of the bag and renames it, so that ``bag info`` has nothing left to warn about."""
    bag = tmp_path / "bag"
    with BagWriter(bag, storage_id=storage) as writer:
        writer.add_topic(TopicInfo("/chatter", "std_msgs/msg/String"))
        writer.write("/chatter", bytes(4) + (2).to_bytes(4, "little") + b"a\0", 10**9, 10**9)
    (bag / "metadata.yaml").unlink()
    extension = ".mcap" if storage == "mcap" else ".db3"
    (bag / f"bag_1{extension}").write_bytes(b"")
    report = recover_bag(bag)
    assert report.readable, report.text()
    assert f"bag_1{extension}: left out" in report.text() and f"renamed to .bag_1{extension}.left-out" in report.text()
    assert "Warning" not in format_bag_info(bag), format_bag_info(bag)
    assert (bag / f".bag_1{extension}.left-out").read_bytes() == b""
    assert sorted(path.name for path in bag.iterdir() if not path.name.startswith(".")) == \
        sorted([f"bag_0{extension}", "metadata.yaml"])


@pytest.fixture(scope="session")
def recording(tmp_path_factory: pytest.TempPathFactory, worker_id: str):
    """One traced recording per test run, shared by the pytest-xdist workers (the first one captures)."""
    shared = tmp_path_factory.getbasetemp() if worker_id == "master" else tmp_path_factory.getbasetemp().parent
    directory = shared / "power_cut_capture"
    with open(shared / "power_cut_capture.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        directory.mkdir(exist_ok=True)
        return load_capture(directory, list(CONFIGS.values()), seconds=2.0, camera=(128, 96))


@needs_strace
@pytest.mark.parametrize("config", list(CONFIGS))
def test_crash_states_of_a_real_recording_recover_every_synced_message(
        recording, tmp_path: Path, config: str) -> None:
    made, trace = recording
    prepared = prepare(made, trace, CONFIGS[config], "strict", tmp_path)
    seeds = list(range(SEED, SEED + STATES))
    print(f"IPC_POWER_CUT_SEED={SEED}: seeds {seeds[0]}..{seeds[-1]} of {config}")
    summary = explore(prepared, seeds, tmp_path)
    print(summary.line())
    assert summary.states == STATES
    assert summary.failures == 0, summary.line()


@pytest.mark.sweep
@needs_strace
@pytest.mark.parametrize("config", list(CONFIGS))
def test_crash_states_of_a_real_recording_sweep(recording, tmp_path: Path, config: str) -> None:
    """``make sweep``: 1000 crash states per configuration from a fresh seed (printed; IPC_POWER_CUT_SEED replays)."""
    made, trace = recording
    prepared = prepare(made, trace, CONFIGS[config], "strict", tmp_path)
    first = int(os.environ.get("IPC_POWER_CUT_SEED") or random.randrange(1_000_000))
    print(f"IPC_POWER_CUT_SEED={first}: 1000 states of {config}")
    summary = explore(prepared, list(range(first, first + 1000)), tmp_path)
    print(summary.line())
    assert summary.failures == 0, summary.line()
