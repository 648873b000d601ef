"""``bag recover`` under fault injection: finished bags cut, padded and zeroed anywhere must come back
readable (rosbags, and the mcap seeking reader) with exactly what was intact before the damage.

One source bag per kind is written with :class:`BagWriter` (no ROS processes); every case works on a
copy. The default run cuts each kind at chosen offsets (at and around record, chunk and page boundaries, the
magic, the header and the summary) and at a few random offsets of a fixed seed (:data:`SEED`); the full sweep
of random cuts (``make sweep``: ``-m sweep``) draws a fresh seed each run, prints it, and
``IPC_RECOVER_SEED=<seed>`` replays it (the default run's seed too).
"""
from __future__ import annotations

import functools
import os
import random
import shutil
import struct
import subprocess
import sys
import tempfile
import textwrap
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader

from baglib.write import mcap_storage
from baglib.tools.info import BagInfoError, format_bag_info
from baglib.format.metadata import TopicInfo
from baglib.tools.repair import RecoveryReport, recover_bag
from ipc_component.cli import main as cli_main

T0 = 1_718_000_000_000_000_000
MESSAGES = 1200
#: Random cuts per kind: of the sweep, and of the fixed-seed subset the default run checks next to the chosen ones.
CUTS = 200
DEFAULT_CUTS = 12
LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
#: The default run's random cuts and zeroed blocks: fixed, so that every run checks the same ones.
SEED = int(os.environ.get("IPC_RECOVER_SEED") or 3_141_592_653)
#: The sweep's: a fresh one each run unless IPC_RECOVER_SEED replays one.
SWEEP_SEED = int(os.environ.get("IPC_RECOVER_SEED") or random.randrange(2**32))
QOS = {"history": "keep_last", "depth": 7, "reliability": "reliable", "durability": "volatile",
       "deadline": {"sec": 9223372036, "nsec": 854775807}, "lifespan": {"sec": 9223372036, "nsec": 854775807},
       "liveliness": "automatic", "liveliness_lease_duration": {"sec": 9223372036, "nsec": 854775807},
       "avoid_ros_namespace_conventions": False}
TOPICS = [TopicInfo("/a", "std_msgs/msg/String", offered_qos_profiles=[QOS]),
          TopicInfo("/b", "std_msgs/msg/String", offered_qos_profiles=[{**QOS, "depth": 1}])]
# bag kind -> (storage id, preset); the small chunks put the cuts into many different chunks
KINDS = {"chunked": ("mcap", ""), "fastwrite": ("mcap", "fastwrite"), "zstd": ("mcap", "zstd_fast"),
         "sqlite3": ("sqlite3", ""), "chunked_frames": ("mcap", ""), "fastwrite_frames": ("mcap", "fastwrite")}
# Kinds with a big message every 100: the writer puts padding records before them (direct I/O in place).
FRAMES = {"chunked_frames", "fastwrite_frames"}
FRAME_BYTES = 300_000


def payload(n: int, kind: str = "chunked") -> bytes:
    """CDR std_msgs/String whose text carries the sequence number (and varies in length)."""
    text = f"seq={n:06d} " + "x" * (FRAME_BYTES if kind in FRAMES and n % 100 == 7 else n * 7919 % 150)
    data = text.encode() + b"\0"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(data)) + data


@pytest.fixture(scope="session", autouse=True)
def announce_seed() -> None:
    print(f"\ntest_recover seeds: default run {SEED}, sweep {SWEEP_SEED} (IPC_RECOVER_SEED=<seed> replays one)")


def write_bag(path: Path, storage_id: str, preset: str, monkeypatch: pytest.MonkeyPatch,
              max_size: int = 0, custom_data: dict[str, str] | None = None, kind: str = "chunked") -> Path:
    from baglib.write.writer import BagWriter
    for name, options in mcap_storage.MCAP_PRESETS.items():
        monkeypatch.setitem(mcap_storage.MCAP_PRESETS, name, replace(options, chunk_size=8192))
    with BagWriter(path, storage_id, max_bagfile_size=max_size, storage_preset_profile=preset,
                   custom_data=custom_data) as writer:
        for topic in TOPICS:
            writer.add_topic(topic)
        for n in range(MESSAGES):
            writer.write(TOPICS[n % 3 == 0].name, payload(n, kind), T0 + n * 1000, T0 + n * 1000)
    return path


@pytest.fixture()
def work(tmp_path: Path) -> Iterator[Path]:
    """Where the damaged copies are recovered: tmpfs if there is one (hundreds of fsyncs per test)."""
    shm = Path("/dev/shm")
    if not (shm.is_dir() and os.access(shm, os.W_OK)):
        yield tmp_path
        return
    path = Path(tempfile.mkdtemp(prefix="test_recover_", dir=shm))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="module")
def sources(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("sources")
    with pytest.MonkeyPatch.context() as monkeypatch:
        return {kind: write_bag(root / kind, *KINDS[kind], monkeypatch, kind=kind) for kind in KINDS}


# --- reading back ----------------------------------------------------------------------------------


def read_rosbags(bag: Path) -> list[tuple[str, int, bytes]]:
    with Reader(bag) as reader:
        return [(connection.topic, timestamp, bytes(raw)) for connection, timestamp, raw in reader.messages()]


def read_mcap(path: Path) -> list[tuple[str, int, bytes]]:
    with open(path, "rb") as file:
        reader = make_reader(file)
        assert reader.get_summary() is not None
        return [(channel.topic, message.log_time, message.data) for _, channel, message in reader.iter_messages()]


def check_readable(bag: Path) -> list[tuple[str, int, bytes]]:
    """Everything both readers see (the same), with metadata.yaml agreeing; in log time order."""
    messages = read_rosbags(bag)
    meta = yaml.load((bag / "metadata.yaml").read_text(), Loader=LOADER)["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["message_count"] == len(messages)
    assert sum(entry["message_count"] for entry in meta["files"]) == len(messages)
    if meta["storage_identifier"] == "mcap":
        from_mcap = [message for entry in meta["files"] for message in read_mcap(bag / entry["path"])]
        assert sorted(from_mcap) == sorted(messages)
    assert len(set(messages)) == len(messages)  # none twice
    return sorted(messages, key=lambda message: message[1])


def original(n: int, kind: str = "chunked") -> tuple[str, int, bytes]:
    return (TOPICS[n % 3 == 0].name, T0 + n * 1000, payload(n, kind))


# --- what must survive a cut -----------------------------------------------------------------------


@functools.cache
def mcap_units(path: Path) -> list[tuple[int, int, set[int]]]:
    """(start, end offset, sequence numbers) of each chunk or unchunked message record of an intact file."""
    raw = path.read_bytes()
    units, position = [], 8
    while True:
        opcode, length = struct.unpack_from("<BQ", raw, position)
        end = position + 9 + length
        if opcode == 0x0F:
            return units
        if opcode == 0x06:  # chunk: its messages are those in its log time range
            start_ns, end_ns = struct.unpack_from("<QQ", raw, position + 9)
            units.append((position, end, set(range((start_ns - T0) // 1000, (end_ns - T0) // 1000 + 1))))
        elif opcode == 0x05:
            (log_time,) = struct.unpack_from("<Q", raw, position + 9 + 6)
            units.append((position, end, {(log_time - T0) // 1000}))
        position = end


def mcap_data_end(path: Path) -> int:
    """Offset of the DataEnd record: the summary section and the footer follow it."""
    raw = path.read_bytes()
    position = 8
    while raw[position] != 0x0F:
        position += 9 + struct.unpack_from("<Q", raw, position + 1)[0]
    return position


def _varint(data: bytes, offset: int) -> tuple[int, int]:
    value = 0
    for index in range(9):
        byte = data[offset + index]
        if index == 8:
            return (value << 8) | byte, offset + 9
        value = (value << 7) | (byte & 0x7F)
        if byte < 0x80:
            return value, offset + index + 1
    raise AssertionError


@functools.cache
def sqlite_leaf_rows(path: Path) -> list[tuple[int, int, set[int]]]:
    """(start, end offset of its page, sequence numbers) of each table leaf page holding message rows."""
    raw = path.read_bytes()
    page_size = struct.unpack_from(">H", raw, 16)[0]
    pages = []
    for number in range(len(raw) // page_size):
        base = number * page_size
        header = base + (100 if number == 0 else 0)
        if raw[header] != 0x0D:
            continue
        rows = set()
        (cells,) = struct.unpack_from(">H", raw, header + 3)
        for cell in range(cells):
            (pointer,) = struct.unpack_from(">H", raw, header + 8 + 2 * cell)
            _, offset = _varint(raw, base + pointer)
            rowid, offset = _varint(raw, offset)
            header_size, types_offset = _varint(raw, offset)
            types = []
            while types_offset < offset + header_size:
                serial, types_offset = _varint(raw, types_offset)
                types.append(serial)
            if len(types) == 4 and types[3] >= 12 and types[3] % 2 == 0:  # (id, topic, time, blob)
                rows.add(rowid - 1)  # ids start at 1, sequence numbers at 0
        if rows:
            pages.append((base, base + page_size, rows))
    return pages


@dataclass
class Expectation:
    must_keep: set[int]
    may_keep: set[int]


def expected(kind: str, source: Path, cut: int) -> Expectation:
    if kind == "sqlite3":
        pages = sqlite_leaf_rows(source)
        return Expectation({n for _, end, rows in pages if end <= cut for n in rows}, set(range(MESSAGES)))
    kept = {n for _, end, numbers in mcap_units(source) if end <= cut for n in numbers}
    return Expectation(kept, kept)  # MCAP: exactly the complete chunks / records


def storage_file(bag: Path) -> Path:
    return next(path for path in bag.iterdir() if path.suffix in (".mcap", ".db3"))


def recover_copy(source: Path, tmp: Path, damage: Callable[[Path], None]) -> tuple[Path, RecoveryReport]:
    """A copy of the bag without its metadata.yaml, damaged, recovered in place."""
    bag = tmp / "bag"
    shutil.rmtree(bag, ignore_errors=True)
    bag.mkdir()
    path = bag / storage_file(source).name
    shutil.copyfile(storage_file(source), path)
    damage(path)
    return bag, recover_bag(bag)


# --- the fault injection ---------------------------------------------------------------------------


def chosen_cuts(kind: str, source: Path) -> list[int]:
    """Cuts where recovery has decisions to make: inside the magic and the header, at, just before and just
    after the start and end of the first, second, a middle and the last chunk / message record (MCAP) or table
    leaf page (SQLite3), at the data end, inside the summary and the footer, and one byte short of the end."""
    path = storage_file(source)
    size = path.stat().st_size
    units = sqlite_leaf_rows(path) if kind == "sqlite3" else mcap_units(path)
    assert len(units) >= 4, f"{kind}: too few records to cut at"
    cuts = {0, 1, 7, 8, 9, 16, size - 1}
    for start, end, _ in (units[0], units[1], units[len(units) // 2], units[-1]):
        cuts |= {start - 1, start, start + 1, start + 9, (start + end) // 2, end - 1, end, end + 1}
    if kind != "sqlite3":
        data_end = mcap_data_end(path)
        cuts |= {data_end, data_end + 5, data_end + 13, (data_end + size) // 2, size - 28, size - 8}
    return sorted(cut for cut in cuts if 0 <= cut < size)


def random_cuts(kind: str, source: Path, seed: int, count: int) -> list[int]:
    size = storage_file(source).stat().st_size
    generator = random.Random(f"{seed}-{kind}")
    return sorted(generator.randrange(size) for _ in range(count))


@pytest.mark.parametrize("kind", list(KINDS))
def test_truncated_at_chosen_and_fixed_seed_cuts(kind: str, sources: dict[str, Path], work: Path) -> None:
    """The default run: every chosen cut, and the first DEFAULT_CUTS random cuts of the fixed seed."""
    source = sources[kind]
    for cut in chosen_cuts(kind, source):
        check_cut(kind, source, cut, work, "chosen")
    for cut in random_cuts(kind, source, SEED, DEFAULT_CUTS):
        check_cut(kind, source, cut, work, f"seed {SEED}")


@pytest.mark.sweep
@pytest.mark.parametrize("kind", list(KINDS))
def test_truncated_anywhere(kind: str, sources: dict[str, Path], work: Path) -> None:
    """The sweep: CUTS random cuts per kind, from a fresh seed each run."""
    source = sources[kind]
    for cut in random_cuts(kind, source, SWEEP_SEED, CUTS):
        check_cut(kind, source, cut, work, f"seed {SWEEP_SEED}")


def check_cut(kind: str, source: Path, cut: int, work: Path, origin: str) -> None:
    """Recover a copy of ``source`` cut at ``cut``: exactly the complete records before the cut come back."""
    bag, report = recover_copy(source, work, lambda path: os.truncate(path, cut))
    expect = expected(kind, storage_file(source), cut)
    context = f"{kind} cut at {cut} ({origin}):\n{report.text()}"
    if not report.readable:  # cut inside the magic or header: nothing there to keep
        assert not expect.must_keep, context
        return
    kept = check_readable(bag)
    numbers = {(timestamp - T0) // 1000 for _, timestamp, _ in kept}
    assert expect.must_keep <= numbers <= expect.may_keep, context
    assert kept == [original(n, kind) for n in sorted(numbers)], context  # intact, none twice
    assert report.files[0].messages == len(kept), context


@pytest.mark.parametrize("kind", sorted(FRAMES))
def test_cut_at_and_inside_padding_records(kind: str, sources: dict[str, Path], work: Path) -> None:
    """The padding records before the big messages (direct I/O in place) are few and small, so random cuts
    rarely hit them: cut at each one's start, inside its header, inside its zeros and right after it."""
    source = sources[kind]
    raw = storage_file(source).read_bytes()
    padding, position = [], 8
    while raw[position] != 0x0F:  # up to the data end
        length = struct.unpack_from("<Q", raw, position + 1)[0]
        if raw[position] == mcap_storage.PADDING_OPCODE:
            padding.append((position, position + 9 + length))
        position += 9 + length
    assert 0 < len(padding) <= MESSAGES // 100  # the big messages of this kind went out in place
    for start, end in padding:
        for cut in (start, start + 5, (start + 9 + end) // 2, end):
            check_cut(kind, source, cut, work, "padding record")


@pytest.mark.parametrize("kind", list(KINDS))
def test_garbage_appended_and_zeroed_block(kind: str, sources: dict[str, Path], work: Path) -> None:
    check_garbage_and_zeroed_blocks(kind, sources[kind], work, SEED)


@pytest.mark.sweep
@pytest.mark.parametrize("kind", list(KINDS))
def test_garbage_appended_and_zeroed_block_fresh_seed(kind: str, sources: dict[str, Path], work: Path) -> None:
    check_garbage_and_zeroed_blocks(kind, sources[kind], work, SWEEP_SEED)


def check_garbage_and_zeroed_blocks(kind: str, source: Path, work: Path, seed: int) -> None:
    size = storage_file(source).stat().st_size
    generator = random.Random(f"{seed}-{kind}-zero")

    def append(path: Path) -> None:
        with open(path, "ab") as file:
            file.write(generator.randbytes(5000))

    bag, report = recover_copy(source, work, append)
    assert report.readable, report.text()
    assert check_readable(bag) == [original(n, kind) for n in range(MESSAGES)], report.text()
    for _ in range(8):
        start = generator.randrange(size // 4, size - 4096)

        def zero(path: Path) -> None:
            with open(path, "r+b") as file:
                file.seek(start)
                file.write(bytes(4096))

        bag, report = recover_copy(source, work, zero)
        context = f"{kind} zeroed at {start} (seed {seed}):\n{report.text()}"
        assert report.readable, context
        kept = check_readable(bag)
        # Whatever lies wholly before the block is kept intact. Without CRCs (this writer's MCAP files
        # and SQLite pages have none) a block inside a record whose length survived cannot be seen:
        # that record (chunk, page) may come back zeroed, and the records after it are kept.
        units = (sqlite_leaf_rows if kind == "sqlite3" else mcap_units)(storage_file(source))
        hit = {n for begin, end, numbers in units if begin < start + 4096 and end > start for n in numbers}
        originals = {original(n, kind): n for n in range(MESSAGES)}
        intact = {originals[message] for message in kept if message in originals}
        assert expected(kind, storage_file(source), start).must_keep <= intact, context
        assert len(kept) - len(intact) <= len(hit), context


@pytest.mark.parametrize("kind", list(KINDS))
def test_missing_metadata_on_intact_bag(kind: str, sources: dict[str, Path], work: Path) -> None:
    bag, report = recover_copy(sources[kind], work, lambda path: None)
    assert report.readable and report.files[0].action == "intact", report.text()
    assert storage_file(bag).read_bytes() == storage_file(sources[kind]).read_bytes()  # untouched
    assert check_readable(bag) == [original(n, kind) for n in range(MESSAGES)]
    regenerated = yaml.safe_load((bag / "metadata.yaml").read_text())
    assert regenerated == yaml.safe_load((sources[kind] / "metadata.yaml").read_text())


def test_split_bag_killed_in_its_last_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """rosbag2-style directory: <dir>_<N> files, the last cut mid-chunk, metadata.yaml stale or gone;
    recovered into -o OUT, leaving the source as it was."""
    bag = write_bag(tmp_path / "split", "mcap", "", monkeypatch, max_size=60_000,
                    custom_data={"robot": "r2"})
    files = sorted(bag.glob("split_*.mcap"), key=lambda path: int(path.stem.split("_")[1]))
    assert len(files) >= 3
    os.truncate(files[-1], files[-1].stat().st_size // 2)
    (bag / "metadata.yaml").unlink()
    before = {path.name: path.read_bytes() for path in bag.iterdir()}
    code = cli_main(["bag", "reindex", str(bag), "-o", str(tmp_path / "out")])
    assert code == 0
    assert {path.name: path.read_bytes() for path in bag.iterdir()} == before
    kept = check_readable(tmp_path / "out")
    assert kept == [original(n) for n in range(len(kept))] and MESSAGES // 2 < len(kept) < MESSAGES
    meta = yaml.safe_load((tmp_path / "out" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert [entry["path"] for entry in meta["files"]] == [path.name for path in files]
    assert meta["custom_data"] == {"robot": "r2"}
    assert [(t["topic_metadata"]["name"], t["topic_metadata"]["offered_qos_profiles"][0]["depth"])
            for t in meta["topics_with_message_count"]] == [("/a", 7), ("/b", 1)]


def test_empty_and_garbage_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for name, content in [("empty_0.mcap", b""), ("empty_0.db3", b""), ("junk_0.mcap", os.urandom(3000)),
                          ("junk_0.db3", b"SQLite format 3\0" + os.urandom(5000))]:
        bag = tmp_path / name.split(".")[0] / name.split(".")[1]
        bag.mkdir(parents=True)
        (bag / name).write_bytes(content)
        assert cli_main(["bag", "recover", str(bag)]) == 1
        out, err = capsys.readouterr()
        assert f"{name}: left out" in out and "cannot recover" in err, (out, err)
        assert (bag / name).read_bytes() == content and sorted(os.listdir(bag)) == [name]


def test_info_names_the_recover_command(sources: dict[str, Path], work: Path) -> None:
    bag, _ = recover_copy(sources["chunked"], work, lambda path: None)
    (bag / "metadata.yaml").unlink()
    with pytest.raises(BagInfoError, match="unfinished bag.*ipc-component bag recover"):
        format_bag_info(bag)
    recover_bag(bag)
    os.truncate(storage_file(bag), 30_000)
    assert f"{storage_file(bag).name} is unfinished: no MCAP footer" in format_bag_info(bag)
    assert "ipc-component bag recover" in format_bag_info(bag)


SQLITE_CRASH_CHILD = textwrap.dedent("""
    import os, sqlite3, sys
    path, mode = sys.argv[1:]
    db = sqlite3.connect(path, isolation_level=None)
    db.execute(f"PRAGMA journal_mode={mode}")
    db.execute("PRAGMA cache_size=1")  # spill: the uncommitted transaction reaches the database file
    db.execute("BEGIN")
    db.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (1, ?, ?)",
                   [(n, b"x" * 3000) for n in range(300)])
    db.execute("COMMIT" if mode == "WAL" else "SELECT 1")  # WAL: committed, never checkpointed
    os._exit(0)  # as SIGKILL would: no rollback, no checkpoint
""")


@pytest.mark.parametrize("mode", ["DELETE", "WAL"])
def test_sqlite_killed_mid_transaction(mode: str, sources: dict[str, Path], tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    shutil.copytree(sources["sqlite3"], bag)
    (bag / "metadata.yaml").unlink()
    path = storage_file(bag)
    subprocess.run([sys.executable, "-c", SQLITE_CRASH_CHILD, str(path), mode], check=True)
    side = path.with_name(path.name + ("-journal" if mode == "DELETE" else "-wal"))
    assert side.exists() and side.stat().st_size
    report = recover_bag(bag)
    assert report.readable, report.text()
    assert not side.exists() and sorted(os.listdir(bag)) == sorted([path.name, "metadata.yaml"])
    kept = check_readable(bag)
    added = 300 if mode == "WAL" else 0  # the committed log's rows count, the rolled-back ones do not
    assert len(kept) == MESSAGES + added
    assert kept[added:] == [original(n) for n in range(MESSAGES)]


def test_interrupted_recover_is_finished_by_the_next(sources: dict[str, Path], tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Killed between moving the journal aside and replacing the database: the rerun finishes."""
    from baglib.tools import repair
    bag = tmp_path / "bag"
    shutil.copytree(sources["sqlite3"], bag)
    path = storage_file(bag)
    subprocess.run([sys.executable, "-c", SQLITE_CRASH_CHILD, str(path), "DELETE"], check=True)
    real_replace = os.replace

    def crash(source: Path, destination: Path) -> None:
        raise KeyboardInterrupt  # the process dies here

    monkeypatch.setattr(repair.os, "replace", crash)
    with pytest.raises(KeyboardInterrupt):
        recover_bag(bag)
    monkeypatch.setattr(repair.os, "replace", real_replace)
    assert not path.with_name(path.name + "-journal").exists()  # moved aside, not lost
    report = recover_bag(bag)
    assert report.readable, report.text()
    assert check_readable(bag) == [original(n) for n in range(MESSAGES)]
    assert sorted(os.listdir(bag)) == sorted([path.name, "metadata.yaml"])
