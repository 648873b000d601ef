"""``bag recover``: make a bag directory that a crash left unfinished readable again.

A recording killed by SIGKILL or a power cut leaves its last MCAP file without data end, summary and
footer (readers refuse it), a SQLite3 file possibly with a hot journal, and no ``metadata.yaml`` for
the current file (rosbag2 writes it only at a split or at the end). Recovering keeps everything
that is intact and provably complete:

* MCAP (:mod:`.repair_mcap`): every record up to the first damage, with message indexes, statistics and the
  summary rebuilt, as ``mcap recover`` does;
* SQLite3 (:mod:`.repair_sqlite`): every committed row (a hot journal rolled back, a log replayed, as any sqlite
  client would);
* ``metadata.yaml`` (version 9) regenerated from the files: per topic its type, serialization
  format, offered QoS profiles and type hash from the MCAP channels / SQLite topics table, custom data
  from the files' own metadata or the old ``metadata.yaml``.

In place (the default) it needs almost no free space, since a recorder killed on a full disk is the common case:
an MCAP file is cut after its last kept record and closed there (a journaled patch, :mod:`.patch_journal`), a
SQLite3 file is recovered by sqlite in the file. Only files that cannot be repaired that way are rebuilt by a
copy, and ``-o OUT`` copies everything into a new directory (for read-only inputs).

It is itself crash-safe: patches are journaled first and finished by the next run; copies are written aside
under temporary names in the same directory, fsynced, and renamed over the originals (or the whole result
renamed to ``-o OUT``); a failed run removes what it wrote. Any file content gives a report, never a traceback.
"""
from __future__ import annotations

import contextlib
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from baglib.format.bag_files import RECOVER_COMMAND, STORAGE_EXTENSIONS, storage_files
from baglib.format.durable import fsync_directory, fsync_file
from baglib.format.mcap_records import MAGIC
from baglib.format.metadata import METADATA_FILENAME, BagMetadata, TopicInfo
from baglib.tools.patch_journal import apply_all, finish_journals
from baglib.tools.recovered import FileReport, Recovered, custom_data_of, load_yaml
from baglib.tools.repair_mcap import recover_mcap
from baglib.tools.repair_sqlite import SQLITE_MAGIC, SQLITE_SIDE_FILES, recover_sqlite

__all__ = ["RECOVER_COMMAND", "FileReport", "RecoveryReport", "recover_bag", "storage_files"]

_TEMP = ".recover-tmp"  # suffix of a file or directory being written by a recover
_ASIDE = ".recover-aside"     # suffix of a SQLite journal moved aside while its database is replaced
LEFT_OUT = ".left-out"  # suffix of a storage file a recovered bag leaves out, renamed out of the way


@dataclass
class RecoveryReport:
    """The outcome of :func:`recover_bag`; ``readable`` says whether the result can be opened."""

    bag: Path
    output: Path
    storage: str = ""
    files: list[FileReport] = field(default_factory=list)
    metadata: BagMetadata | None = None
    error: str = ""

    @property
    def readable(self) -> bool:
        return self.metadata is not None and not self.error

    def text(self) -> str:
        lines = [f"Recovering {self.bag}" + (f" into {self.output}" if self.output != self.bag else "")
                 + (f" ({self.storage})" if self.storage else "") + ":"]
        lines += [f"  {report.line()}" for report in self.files]
        if self.error:
            lines.append(f"Not recovered: {self.error}")
        elif self.metadata is not None:
            lines.append(f"Wrote {self.output / METADATA_FILENAME}: {len(self.metadata.files)} files, "
                         f"{self.metadata.message_count} messages, {len(self.metadata.topics)} topics")
        return "\n".join(lines)


def recover_bag(bag: str | os.PathLike[str], output: str | os.PathLike[str] | None = None) -> RecoveryReport:
    """Recover the bag directory ``bag`` in place, or into the new directory ``output``."""
    bag = Path(bag)
    out = Path(output) if output is not None else bag
    report = RecoveryReport(bag, out)
    if not bag.is_dir():
        report.error = f"{bag} is not a directory"
        return report
    if out != bag and out.exists():
        report.error = f"{out} exists (a recovered bag is never written into an existing path)"
        return report
    try:
        _finish_interrupted(bag)
        target = bag if out == bag else out.with_name(f".{out.name}{_TEMP}")
        if target != bag:
            shutil.rmtree(target, ignore_errors=True)
            target.mkdir(parents=True)
        try:
            _recover_into(bag, target, report)
            if report.readable and target != bag:
                fsync_directory(target)
                target.rename(out)
                fsync_directory(out.parent)
        finally:
            if target != bag:
                shutil.rmtree(target, ignore_errors=True)
    except OSError as error:
        report.error = f"{error.filename or bag}: {error.strerror or error}"
        report.metadata = None
        with contextlib.suppress(OSError):  # leave no half-written copy behind (a full disk stays full)
            _finish_interrupted(bag)
    return report


def _recover_into(bag: Path, target: Path, report: RecoveryReport) -> None:
    paths = storage_files(bag)
    kinds = {_storage_of(path) for path in paths}
    if not paths:
        report.error = f"no .mcap or .db3 files in {bag}"
        return
    if len(kinds) > 1:
        report.error = f"files of different storages ({', '.join(sorted(kinds))}) in one bag"
        return
    report.storage = kinds.pop()
    recovered = []
    left_out = []
    for path in paths:
        if report.storage == "mcap":
            result = recover_mcap(path)
        else:
            result = recover_sqlite(path, target / f".{path.name}{_TEMP}", in_place=target == bag)
        report.files.append(result.report)
        if result.report.action != "left out":
            recovered.append(result)
        else:
            left_out.append((path, result.report))
    if not recovered:
        report.error = "no file holds anything recoverable"
        return
    metadata = _bag_metadata(bag, report.storage, recovered)
    serialized = metadata.to_yaml()
    written, patches = [], []
    for result in recovered:
        destination = target / result.info.path
        patch = result.patch(serialized) if target == bag and result.patch is not None else None
        if patch is not None:
            patches.append(patch)
        elif result.write is not None:
            temporary = target / f".{result.info.path}{_TEMP}"
            result.write(temporary, serialized)
            fsync_file(temporary)
            written.append((temporary, destination))
        elif target != bag:
            shutil.copyfile(bag / result.info.path, destination)
            fsync_file(destination)
    apply_all(patches)
    for temporary, destination in written:
        _replace(temporary, destination)
    metadata.write(target)
    report.metadata = metadata
    if target == bag:
        for path, file_report in left_out:
            _set_aside(path, file_report)


def _set_aside(path: Path, file_report: FileReport) -> None:
    """Rename a storage file the recovered bag leaves out (nothing readable in it: a split file prepared just
    before the crash, whose header never reached the file) to ``.<name>.left-out``, its SQLite side files too:
    its bytes are kept, and ``bag info`` no longer takes it for a file that still needs recovering."""
    for source in [path, *(path.with_name(path.name + suffix) for suffix in SQLITE_SIDE_FILES)]:
        if source.exists():
            source.rename(source.with_name(f".{source.name}{LEFT_OUT}"))
    fsync_directory(path.parent)
    file_report.reasons.append(f"renamed to .{path.name}{LEFT_OUT}")


def _bag_metadata(bag: Path, storage: str, recovered: list[Recovered]) -> BagMetadata:
    """The regenerated ``metadata.yaml``: topics in order of first appearance, files in order."""
    topics: dict[str, TopicInfo] = {}
    custom_data = _old_custom_data(bag)
    for result in recovered:
        for topic in result.topics:
            topics.setdefault(topic.name, topic)
        custom_data = custom_data or result.custom_data
    return BagMetadata(storage, list(topics.values()), [result.info for result in recovered], custom_data)


def _old_custom_data(bag: Path) -> dict[str, str] | None:
    with contextlib.suppress(Exception):  # whatever the old file holds, it is only a hint
        document = load_yaml((bag / METADATA_FILENAME).read_text())
        return custom_data_of(document.get("rosbag2_bagfile_information", document))
    return None


def _storage_of(path: Path) -> str:
    """The storage a file belongs to: by its magic, else by its extension."""
    with open(path, "rb") as file:
        start = file.read(len(SQLITE_MAGIC))
    if start.startswith(MAGIC):
        return "mcap"
    if start == SQLITE_MAGIC:
        return "sqlite3"
    return STORAGE_EXTENSIONS[path.suffix]


# --- crash safety ----------------------------------------------------------------------------


def _replace(temporary: Path, destination: Path) -> None:
    """Rename a written file over ``destination``; a database's journal is moved aside meanwhile.

    A journal left next to the new database would be "rolled back" into it. The aside journal
    exists only while the complete temporary file does, so :func:`_finish_interrupted` knows
    whether to roll the replacement forward.
    """
    for suffix in SQLITE_SIDE_FILES:
        side = destination.with_name(destination.name + suffix)
        if side.exists():
            side.rename(destination.with_name(f".{destination.name}{suffix}{_ASIDE}"))
    os.replace(temporary, destination)
    fsync_directory(destination.parent)
    for suffix in SQLITE_SIDE_FILES:
        destination.with_name(f".{destination.name}{suffix}{_ASIDE}").unlink(missing_ok=True)


def _finish_interrupted(bag: Path) -> None:
    """Complete a replacement or an in-place patch an interrupted recover began, and remove what it left
    half-written."""
    finish_journals(bag)
    for aside in bag.glob(f".*{_ASIDE}"):
        database = aside.name[1:-len(_ASIDE)]
        for suffix in SQLITE_SIDE_FILES:
            database = database.removesuffix(suffix)
        temporary = bag / f".{database}{_TEMP}"
        if temporary.exists():  # complete (it was fsynced before the journal moved): finish
            _replace(temporary, bag / database)
        aside.unlink(missing_ok=True)
    for leftover in bag.glob(f".*{_TEMP}*"):
        if leftover.is_dir():
            shutil.rmtree(leftover, ignore_errors=True)
        else:
            leftover.unlink(missing_ok=True)
