"""The bag writer: rosbag2's ``SequentialWriter`` for already-serialized messages.

It owns the bag directory (``<uri>/metadata.yaml`` plus ``<name>_<N>.mcap`` or ``.db3``), splits
files by size or duration, and keeps ``metadata.yaml`` true to the files: it is rewritten
atomically at every split (so a crash later still leaves a readable bag of the closed files) and
at close. A split does not wait for the full file: the next one is prepared ahead, and the full one is
finished (last chunk, summary, fsync) and then listed in ``metadata.yaml`` by a thread of its own, while
writes go on into the next file. The last messages of chosen topics (latched ones: :meth:`BagWriter.repeat_topic`)
are written again at the start of every next file, so that each file can be used on its own. A failed write (disk full, ...) never leaves an unreadable bag behind: the current file is
finalized with what reached it, ``metadata.yaml`` counts exactly that, and the caller gets a
:class:`BagWriteError` naming the file and the OS reason.
"""
from __future__ import annotations

import contextlib
import dataclasses
import errno
import os
import shutil
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn, Protocol

from baglib.write.mcap_storage import McapStorage
from baglib.format.cdr_fast import CdrData
from baglib.format.message_definitions import message_definition, type_hash_of_definition
from baglib.format.durable import fsync_directory
from baglib.format.metadata import BagMetadata, FileInfo, TopicInfo
from baglib.write.sqlite_storage import SqliteStorage

__all__ = ["BagExistsError", "BagWriteError", "BagWriter", "SplitCallback"]

#: Called with (closed file, opened file); the opened file is ``""`` when the bag is closed.
SplitCallback = Callable[[str, str], None]

_NS_PER_S = 1_000_000_000


class BagWriteError(OSError):
    """The bag could not be created or written; ``filename`` is the path, ``strerror`` the reason.

    When it is raised by a write, the bag on disk is already closed and readable, holding
    everything written before the failure.
    """


class BagExistsError(FileExistsError):
    """The bag directory already exists; a bag is never written into (or over) an existing one."""


class _Storage(Protocol):
    """What the writer needs from a storage file (see McapStorage and SqliteStorage)."""

    path: Path
    error: OSError | None
    readable: bool

    @property
    def size(self) -> int: ...

    def add_topic(self, topic: TopicInfo, definition: tuple[str, str]) -> None: ...

    def write(
        self, topic: str, data: CdrData, log_time_ns: int, publish_time_ns: int
    ) -> None: ...

    def flush(self) -> None: ...

    def write_gathered(self) -> None: ...

    def close(self, serialized_metadata: str = "") -> FileInfo: ...


#: Share of the size or duration limit at which the next file is created ahead of the split.
PREPARE_AT = 0.9


@dataclasses.dataclass
class _ClosingFile:
    """A file being finished in the background after a split (see :meth:`BagWriter._split`)."""

    storage: _Storage
    entry: FileInfo  # its metadata entry as the writer counted it, for the counts while it closes
    opened: Path  # the file that took its place
    listed: BagMetadata  # metadata.yaml once it is closed: it listed, the files circular recording drops not
    dropped: list[FileInfo]  # the oldest files, deleted once it is closed (max_bag_files)
    done: threading.Event = dataclasses.field(default_factory=threading.Event)
    info: FileInfo | None = None  # what the storage says it holds, once closed
    failure: Exception | None = None  # what finishing it raised (storages report I/O errors, never raise them)

_STORAGES: dict[str, type[McapStorage] | type[SqliteStorage]] = {
    McapStorage.storage_id: McapStorage,
    SqliteStorage.storage_id: SqliteStorage,
}


class BagWriter:
    """Write a rosbag2 bag (metadata version 9) from CDR-serialized messages. Thread-safe.

    Args:
        uri: the bag directory, which must not exist yet; empty or ``None`` means
            ``rosbag2_YYYY_MM_DD-HH_MM_SS`` in the current directory.
        storage_id: ``"mcap"`` (also for ``""``) or ``"sqlite3"``.
        max_bagfile_size: split when the current file reaches this many bytes (0: never).
        max_bagfile_duration: split when a message is this many seconds newer than the current
            file's first message (0: never).
        storage_preset_profile: rosbag2's presets: ``none``, ``fastwrite``, ``zstd_fast``,
            ``zstd_small`` for MCAP; ``none``, ``resilient`` for sqlite3.
        custom_data: string pairs stored in ``metadata.yaml``.
        on_split: called after a file is closed and listed in ``metadata.yaml``, with its path and the
            next file's path (``""`` when the bag is closed); it runs with the writer's (reentrant) lock
            held, on the writing thread or on the thread that finished the file after a split.
        gather_bytes: with direct I/O (MCAP), gather up to this many bytes into one write (0: write at once).
            Then a big buffer of :meth:`write`'s data is written after the call returns, from where it is: it
            must not change before the next :meth:`flush` or :meth:`close` returns. The
            recorder gathers (its messages do not change once published); see baglib.write.direct_file.

    Raises:
        ValueError: unknown storage id or preset, negative limits.
        BagExistsError: ``uri`` exists.
        BagWriteError: the directory or first file cannot be created.
    """

    def __init__(
        self,
        uri: str | Path | None = None,
        storage_id: str = "mcap",
        max_bagfile_size: int = 0,
        max_bagfile_duration: float | int = 0,
        storage_preset_profile: str = "",
        custom_data: dict[str, str] | None = None,
        on_split: SplitCallback | None = None,
        max_bag_files: int = 0,
        gather_bytes: int = 0,
    ) -> None:
        storage_id = storage_id or "mcap"
        if storage_id not in _STORAGES:
            raise ValueError(
                f"unsupported storage_id {storage_id!r}: use one of {', '.join(map(repr, _STORAGES))}"
            )
        self._storage_class = _STORAGES[storage_id]
        if storage_preset_profile not in self._storage_class.presets:
            raise ValueError(
                f"unknown {storage_id} storage_preset_profile {storage_preset_profile!r}: "
                f"use one of {', '.join(repr(name) for name in self._storage_class.presets if name)}"
            )
        if max_bagfile_size < 0 or max_bagfile_duration < 0:
            raise ValueError("max_bagfile_size and max_bagfile_duration must not be negative")
        if max_bag_files < 0 or (max_bag_files and not (max_bagfile_size or max_bagfile_duration)):
            raise ValueError("max_bag_files needs splitting (max_bagfile_size or max_bagfile_duration) and must "
                             "not be negative")
        if custom_data is not None and not all(
            isinstance(key, str) and isinstance(value, str) for key, value in custom_data.items()
        ):
            raise ValueError("custom_data keys and values must be strings")

        self._preset = storage_preset_profile
        self._max_bag_files = int(max_bag_files)
        self._gather_bytes = gather_bytes
        #: Files deleted by circular recording (max_bag_files), oldest first, and their messages per topic. The
        #: list is replaced, never changed, so that it can be read without the lock.
        self.deleted_files: list[str] = []
        self._deleted_counts: dict[str, int] = {}
        self._identity: tuple[int, int] | None = None  # (st_dev, st_ino) of the current file
        self._prepared: _Storage | None = None  # the next file, created ahead of the split
        self._closing: _ClosingFile | None = None  # the previous file, finished in the background
        self._syncing: threading.Thread | None = None  # the fsync of the current file, if one is running
        self._sync_error: OSError | None = None  # its failure, raised by the next call
        self._prepare_failed = False
        self._max_size = int(max_bagfile_size)
        self._max_duration_ns = round(max_bagfile_duration * _NS_PER_S)
        self._on_split = on_split
        self._lock = threading.RLock()
        self._path = Path(uri) if uri else Path.cwd() / time.strftime("rosbag2_%Y_%m_%d-%H_%M_%S")
        self._metadata = BagMetadata(storage_id, custom_data=dict(custom_data) if custom_data else None)
        self._topics: dict[str, TopicInfo] = {}
        self._definitions: dict[str, tuple[str, str]] = {}
        self._closed_bytes = 0
        self._file_index = 0
        self._file_counts: dict[str, int] = {}
        self._file_first_ns: int | None = None
        self._file_last_ns: int | None = None
        self._failure: BagWriteError | None = None
        self._closed = False
        # Topics whose last messages start every next file: (CDR bytes, log time, publish time) each.
        self._repeat: dict[str, deque[tuple[bytes, int, int]]] = {}
        self._last_written: tuple[int, int] | None = None  # (log, publish) time of the latest message written
        self._file_fresh = True  # the current file holds no message but repeated ones: it is never split off
        #: Per topic, copies written again (repeat_topic, or ``write(repeat=True)``); replaced, never changed,
        #: so that it can be read without the lock.
        self.repeated_counts: dict[str, int] = {}

        try:
            created = [self._path, *(parent for parent in self._path.parents if not parent.exists())]
            self._path.mkdir(parents=True)
        except FileExistsError:
            raise BagExistsError(
                errno.EEXIST,
                "bag directory already exists; choose a new uri (bags are never overwritten)",
                str(self._path),
            ) from None
        except OSError as error:
            raise BagWriteError(
                error.errno, f"cannot create bag directory: {error.strerror}", str(self._path),
            ) from error
        for directory in created:  # its name (and a new parent's) must survive a power loss too
            with contextlib.suppress(OSError):  # best effort: a parent we may not read still takes the bag
                fsync_directory(directory.parent)
        self._current_path: Path | None = None
        try:
            self._storage: _Storage | None = self._open_storage()
        except BagWriteError:
            with contextlib.suppress(OSError):
                self._path.rmdir()
            raise

    # --- public API ---------------------------------------------------------------------------

    @property
    def path(self) -> Path:
        """The bag directory."""
        return self._path

    @property
    def current_file(self) -> Path | None:
        """The storage file being written (``None`` once closed or after a failure). Readable without the lock
        (by a stats reader while a write holds it): during a split it is the previous file until the next one
        is open, never ``None``."""
        return self._current_path

    @property
    def files(self) -> list[Path]:
        """All storage files listed in the bag so far, the current one included."""
        with self._lock:
            paths = [self._path / info.path for info in self._metadata.files]
            if self._closing is not None:
                paths.append(self._closing.storage.path)
            if self._storage is not None:
                paths.append(self._storage.path)
            return paths

    @property
    def topics(self) -> list[TopicInfo]:
        return list(self._metadata.topics)

    @property
    def topic_message_counts(self) -> dict[str, int]:
        """Messages written per topic (every added topic is present, possibly with 0)."""
        with self._lock:
            counts = self._metadata.topic_message_counts()
            unlisted = [self._file_counts]
            if self._closing is not None:
                unlisted.append(self._closing.entry.topic_message_counts)
            for file_counts in unlisted:
                for name, count in file_counts.items():
                    counts[name] += count
            return counts

    @property
    def written_message_counts(self) -> dict[str, int]:
        """Messages written per topic since the bag was opened: :attr:`topic_message_counts` plus what the files
        circular recording deleted held."""
        with self._lock:  # reentrant: the two counts of one moment
            counts = self.topic_message_counts
            for name, count in self._deleted_counts.items():
                counts[name] = counts.get(name, 0) + count
        return counts

    @property
    def message_count(self) -> int:
        return sum(self.topic_message_counts.values())

    @property
    def bytes_written(self) -> int:
        """Size of the closed files plus what the current file holds or is about to."""
        with self._lock:
            open_files = [self._storage, self._closing.storage if self._closing is not None else None]
            return self._closed_bytes + sum(storage.size for storage in open_files if storage is not None)

    @property
    def closed(self) -> bool:
        return self._closed

    def update_custom_data(self, pairs: dict[str, str]) -> None:
        """Add or replace ``custom_data`` pairs; they are in ``metadata.yaml`` from its next write (a split or
        the close) on. Never waits for the writer: the map is replaced as a whole, which readers see at once."""
        if not all(isinstance(key, str) and isinstance(value, str) for key, value in pairs.items()):
            raise ValueError("custom_data keys and values must be strings")
        self._metadata.custom_data = {**(self._metadata.custom_data or {}), **pairs}

    def add_topic(self, info: TopicInfo, definition: tuple[str, str] | None = None) -> None:
        """Make a topic known; it is listed in the bag even if no message is ever written.

        Adding a topic again is a no-op; adding its name with another type is an error. An empty
        ``type_description_hash`` is filled in from the locally installed type when the type is described with
        the installed definition (another definition keeps the hash it came with, which readers check it
        against; empty when it had none). ``definition`` is the
        type's ``(encoding, text)`` as another bag recorded it (a merge copies its inputs'); without
        it, the locally installed one. A type is described once, by its first topic's definition.

        Raises:
            MessageDefinitionNotFoundError: no ``definition`` is given and the type's is not
                installed here, so the bag could not describe it.
            ValueError: the name is already used by another type.
            BagWriteError: the storage failed (the bag is then closed, see class doc).
        """
        with self._lock:
            self._require_writable()
            existing = self._topics.get(info.name)
            if existing is not None:
                if existing.type != info.type:
                    raise ValueError(
                        f"topic {info.name} already recorded as {existing.type}, not {info.type}"
                    )
                return
            definition = self._definitions.get(info.type) or definition or message_definition(info.type)
            if not info.type_description_hash:
                info = dataclasses.replace(info, type_description_hash=type_hash_of_definition(info.type, definition))
            assert self._storage is not None
            try:
                self._storage.add_topic(info, definition)
            except OSError as error:
                self._fail(error)
            if self._prepared is not None:
                try:
                    self._prepared.add_topic(info, definition)
                except OSError:
                    self._discard_prepared()  # the split will create the file itself, and report a failure
            self._definitions[info.type] = definition
            self._topics[info.name] = info
            self._metadata.topics.append(info)
            self._file_counts[info.name] = 0

    def repeat_topic(self, topic: str, depth: int) -> None:
        """Write the last ``depth`` messages of ``topic`` again at the start of every file that follows a split
        (rosbag2 Rolling's ``--repeat-transient-local``), stamped with the receive and publish times of the last
        message written to the previous file, as rosbag2 does (a file played alone has no gap before its own
        messages). Their data is unchanged: a header stamp in the message is the original one.

        Raises:
            KeyError: the topic was not added.
        """
        with self._lock:
            if topic not in self._topics:
                raise KeyError(f"unknown topic {topic!r}: add_topic() it first")
            self._repeat[topic] = deque(self._repeat.get(topic, ()), maxlen=depth)

    def write(
        self, topic: str, data: CdrData, log_time_ns: int, publish_time_ns: int, split: bool | None = None,
        repeat: bool = False,
    ) -> None:
        """Write one CDR-serialized message (with its 4-byte encapsulation header).

        ``log_time_ns`` is the receive time (bag order, splitting, metadata times);
        ``publish_time_ns`` the source time. ``split``: None splits first if the current file is full, True
        splits first (unless the file is empty), False never (a caller that chooses where files begin, see
        :meth:`split_due`). ``data`` may be reused after the call, unless the writer gathers writes
        (``gather_bytes``). ``repeat``: a copy of an earlier message (a latched one at the start of a
        snapshot), counted in :attr:`repeated_counts` as well as in the file.

        Raises:
            KeyError: the topic was not added.
            BagWriteError: the storage failed; the bag is closed and readable up to here.
        """
        with self._lock:
            self._require_writable()
            if topic not in self._topics:
                raise KeyError(f"unknown topic {topic!r}: add_topic() it first")
            self._settle_background()
            if self._split_due(log_time_ns) if split is None else (split and not self._file_fresh):
                self._split()
            self._put(topic, data, log_time_ns, publish_time_ns)
            if repeat:
                self._count_repeat(topic)
            else:
                self._file_fresh = False
                self._last_written = (log_time_ns, publish_time_ns)
                kept = self._repeat.get(topic)
                if kept is not None:
                    kept.append((bytes(data), log_time_ns, publish_time_ns))
            if self._prepared is None and self._split_near(log_time_ns):
                self._prepare_next()

    def _put(self, topic: str, data: CdrData, log_time_ns: int, publish_time_ns: int) -> None:
        """Write one message into the current file and count it there."""
        assert self._storage is not None
        try:
            self._storage.write(topic, data, log_time_ns, publish_time_ns)
        except OSError as error:
            self._fail(error)
        self._file_counts[topic] += 1
        if self._file_first_ns is None or log_time_ns < self._file_first_ns:
            self._file_first_ns = log_time_ns
        if self._file_last_ns is None or log_time_ns > self._file_last_ns:
            self._file_last_ns = log_time_ns

    def _count_repeat(self, topic: str) -> None:
        self.repeated_counts = {**self.repeated_counts, topic: self.repeated_counts.get(topic, 0) + 1}

    def _write_repeats(self) -> None:
        """Start the new file with the kept messages of the repeated topics, oldest first, at the time of the
        last message of the previous file (see :meth:`repeat_topic`)."""
        if self._last_written is None:
            return
        log_time_ns, publish_time_ns = self._last_written
        kept = sorted(((entry[1], topic, entry[0]) for topic, entries in self._repeat.items() for entry in entries),
                      key=lambda item: item[0])
        for _, topic, data in kept:
            self._put(topic, data, log_time_ns, publish_time_ns)
            self._count_repeat(topic)

    def split_due(self, log_time_ns: int) -> bool:
        """Whether a message received at ``log_time_ns`` would go to a new file (the current one is full)."""
        with self._lock:
            return self._storage is not None and self._split_due(log_time_ns)

    def split(self) -> None:
        """Close the current file (complete with its summary, listed in ``metadata.yaml`` on return) and
        continue in the next one."""
        with self._lock:
            self._require_writable()
            self._split()
            self._settle_closing(wait=True)

    def flush(self) -> None:
        """Make every message written so far a complete record in the current file, handed to the OS: a
        crash of the process after this cannot lose them (the recorder calls it every flush_interval).

        Raises:
            BagWriteError: the storage failed (the bag is then closed, see class doc).
        """
        self._on_current_file(lambda storage: storage.flush())

    def write_gathered(self) -> None:
        """Let the storage start writing what it gathered (the recorder calls this whenever it has no more
        messages at hand, so the disk never waits for a gather to fill); it does not wait for the writes.

        Raises:
            BagWriteError: the storage failed (the bag is then closed, see class doc).
        """
        self._on_current_file(lambda storage: storage.write_gathered())

    def sync(self) -> None:
        """:meth:`flush`, then fsync the current file (what was written survives a power loss too) on a thread
        of its own. Returns at once: an fsync can take a hundred milliseconds or more while the disk is busy,
        and every message would wait behind it. Its failure is raised by the next call, as a failed write. While
        the previous fsync still runs, none is started (the next call covers what this one would have)."""
        self._on_current_file(self._start_fsync)

    def _start_fsync(self, storage: _Storage) -> None:
        storage.flush()
        if self._syncing is not None and self._syncing.is_alive():
            return
        fd = os.open(storage.path, os.O_RDONLY)  # fsync covers the file, whichever descriptor asks
        self._syncing = threading.Thread(target=self._fsync, args=(fd,), name=f"bag_sync:{storage.path.name}",
                                         daemon=True)
        self._syncing.start()

    def _fsync(self, fd: int) -> None:
        """The directory first, then the file: once the file's fsync returns, its name is durable too (it was
        created before this sync began), and so is the removal of a SQLite3 rollback journal by a commit before
        it; otherwise a power loss can take the whole file with it, or roll a committed transaction back."""
        try:
            fsync_directory(self._path)
            os.fsync(fd)
        except OSError as error:
            self._sync_error = error
        finally:
            os.close(fd)

    def _on_current_file(self, action: Callable[[_Storage], None]) -> None:
        with self._lock:
            self._require_writable()
            self._settle_background()
            assert self._storage is not None
            try:
                action(self._storage)
            except OSError as error:
                self._fail(error)

    def discard(self) -> None:
        """Close and delete this bag before anything was written to it (its recorder refused to start)."""
        with self._lock:
            self._closed = True
            self._discard_prepared()
            if self._storage is not None:
                self._storage.close()
                self._storage = self._current_path = None
            shutil.rmtree(self._path, ignore_errors=True)

    def check_files(self) -> None:
        """Raise BagWriteError (and close the bag) if the current file was deleted or replaced on disk: writes
        would go on into an unlinked file or a stranger's, and nothing of them would ever be readable."""
        with self._lock:
            if self._closed or self._failure is not None or self._storage is None:
                return
            self._settle_closing(wait=True)
            try:
                status = os.stat(self._storage.path)
                identity: tuple[int, int] | None = (status.st_dev, status.st_ino)
            except FileNotFoundError:
                identity = None
            if identity != self._identity:
                what = "deleted" if identity is None else "replaced by another file"
                closed = self._storage.path
                self._close_storage()  # into the unlinked or displaced file: none of it is readable by name
                self._metadata.files = [info for info in self._metadata.files if info.path != closed.name]
                self._stop(OSError(errno.ENOENT, f"the bag file was {what} while recording"), closed)

    def close(self) -> None:
        """Close the current file and write ``metadata.yaml``; further calls do nothing.

        Raises:
            BagWriteError: finishing the file or writing ``metadata.yaml`` failed (whatever could
                be saved is saved). An error already raised by :meth:`write` is not raised again.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._discard_prepared()
            self._settle_closing(wait=True)  # may raise the failure of the file split off last
            closed: Path | None = None
            error: BagWriteError | None = None
            cause: OSError | None = None
            if self._storage is not None:
                closed = self._storage.path
                cause = self._close_storage()
                if cause is not None:
                    error = self._error(cause, "cannot finish bag file", closed)
            try:
                self._metadata.write(self._path)
            except OSError as metadata_error:
                if error is None:
                    error = self._error(metadata_error, "cannot write metadata.yaml")
                    cause = metadata_error
            if closed is not None and self._on_split is not None:
                self._on_split(str(closed), "")
            if error is not None:
                raise error from cause

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # --- internals ----------------------------------------------------------------------------

    def _require_writable(self) -> None:
        if self._closed:
            raise ValueError(f"bag {self._path} is closed")
        if self._failure is not None:
            raise BagWriteError(
                self._failure.errno,
                f"writing stopped after an earlier failure: {self._failure.strerror}",
                self._failure.filename,
            )

    def _file_path(self) -> Path:
        return self._path / f"{self._path.name}_{self._file_index}{self._storage_class.extension}"

    def _open_storage(self) -> _Storage:
        """Make the next file current: the one prepared ahead (see :meth:`_prepare_next`), or a new one."""
        storage, self._prepared = self._prepared, None
        if storage is None:
            storage = self._create_storage(self._file_path())
        self._file_counts = dict.fromkeys(self._topics, 0)
        self._file_first_ns = self._file_last_ns = None
        self._file_fresh = True
        status = os.stat(storage.path)
        self._identity = (status.st_dev, status.st_ino)
        self._current_path = storage.path
        return storage

    def _create_storage(self, path: Path) -> _Storage:
        """Create a storage file with every known topic in it."""
        opening = dataclasses.replace(self._metadata, files=[*self._metadata.files, FileInfo(path.name)])
        try:
            storage: _Storage = self._storage_class(path, self._preset, opening.to_yaml(), self._gather_bytes)
        except OSError as error:
            if not isinstance(error, FileExistsError):
                path.unlink(missing_ok=True)  # a partial file of ours; it holds no messages
            raise self._error(error, "cannot create bag file", path) from error
        try:
            for topic in self._metadata.topics:
                storage.add_topic(topic, self._definitions[topic.type])
        except OSError as error:
            storage.close()
            path.unlink(missing_ok=True)
            raise self._error(error, "cannot create bag file", path) from error
        return storage

    def _split_near(self, log_time_ns: int) -> bool:
        """The current file is at PREPARE_AT of its size or duration limit: time to prepare the next one."""
        if self._file_first_ns is None or self._prepare_failed:
            return False
        assert self._storage is not None
        if self._max_size and self._storage.size >= PREPARE_AT * self._max_size:
            return True
        return bool(self._max_duration_ns) and \
            log_time_ns - self._file_first_ns > PREPARE_AT * self._max_duration_ns

    def _prepare_next(self) -> None:
        """Create the next file (header, opening metadata, topics) before the split needs it, so that the split
        itself only closes the current file and switches. A failure here is left for the split to report."""
        self._file_index += 1
        try:
            self._prepared = self._create_storage(self._file_path())
        except BagWriteError:
            self._prepare_failed = True
        finally:
            self._file_index -= 1

    def _discard_prepared(self) -> None:
        """Remove a prepared file that will not be used (the bag closes first, or it could not be completed)."""
        prepared, self._prepared = self._prepared, None
        if prepared is not None:
            prepared.close()
            prepared.path.unlink(missing_ok=True)

    def _split_due(self, log_time_ns: int) -> bool:
        if self._file_fresh:
            return False  # never split off an empty file (or one of repeated messages only: one file per message)
        assert self._storage is not None
        if self._max_size and self._storage.size >= self._max_size:
            return True
        return bool(self._max_duration_ns) and log_time_ns - self._file_first_ns > self._max_duration_ns

    def _split(self) -> None:
        """Switch to the next file at once and finish the full one on a thread of its own: closing a file
        (its last chunk, summary and fsync, then ``metadata.yaml``) takes tens of milliseconds, during which
        every message would wait, and each split would show as a spike in the receive-to-write latency."""
        self._settle_closing(wait=True)  # files are listed in order; a failure of the last one stops here
        storage, entry, closing_metadata = self._detach_storage()
        self._file_index += 1
        self._prepare_failed = False
        try:
            self._storage = self._open_storage()
        except BagWriteError as open_error:
            self._current_path = None
            self._list_closed(storage, storage.close(closing_metadata.to_yaml()))
            self._failure = open_error
            self._write_metadata_quietly()
            if self._on_split is not None:
                self._on_split(str(storage.path), "")
            raise
        listed = [*self._metadata.files, entry]
        # circular recording keeps the newest max_bag_files files, the new current one among them
        drop = max(0, len(listed) - (self._max_bag_files - 1)) if self._max_bag_files else 0
        closing = self._closing = _ClosingFile(storage, entry, self._storage.path,
                                               dataclasses.replace(closing_metadata, files=listed[drop:]),
                                               listed[:drop])
        threading.Thread(target=self._close_in_background, args=(closing, closing_metadata),
                         name=f"bag_close:{storage.path.name}", daemon=True).start()
        self._write_repeats()

    def _close_in_background(self, closing: _ClosingFile, metadata: BagMetadata) -> None:
        """Finish the file, write ``metadata.yaml`` naming it, then delete what circular recording drops: all
        without the writer's lock (the fsyncs take milliseconds), and before ``done``, so that every later
        ``metadata.yaml`` (written only after waiting for ``done``) replaces this one."""
        try:
            closing.info = closing.storage.close(metadata.to_yaml())
            if closing.storage.error is None:  # a failure is raised to the writing thread, at its next call
                with contextlib.suppress(OSError):  # the next split or the close writes it again
                    closing.listed.write(self._path)
                for info in closing.dropped:
                    with contextlib.suppress(FileNotFoundError):
                        (self._path / info.path).unlink()
        except Exception as exc:  # noqa: BLE001 - a bug here must stop the bag, not leave the writer waiting
            closing.failure = exc
        finally:
            closing.done.set()
        if closing.info is not None and closing.storage.error is None:
            with self._lock:
                if self._closing is closing:
                    self._settle_closing()

    def _settle_background(self) -> None:
        """Take in what the background threads finished: a split-off file (see :meth:`_settle_closing`), and
        a failed fsync, which stops the bag like a failed write."""
        self._settle_closing()
        error, self._sync_error = self._sync_error, None
        if error is not None:
            self._fail(error)

    def _settle_closing(self, wait: bool = False) -> None:
        """Account for a file finished in the background (listed, dropped files gone, ``on_split``); with
        ``wait``, wait for it first. If it failed, the bag stops as after a failed write (raises)."""
        closing = self._closing
        if closing is None or not (wait or closing.done.is_set()):
            return
        closing.done.wait()
        self._closing = None
        if closing.info is None:  # left unfinished, out of metadata.yaml: `bag recover` completes it
            error: OSError | None = OSError(errno.EIO, f"finishing the file failed: {closing.failure!r}")
        else:
            error = self._list_closed(closing.storage, closing.info)
        if error is not None:
            if self._storage is not None:
                self._close_storage()  # what reached the next file is kept too
            self._stop(error, closing.storage.path)
        dropped = {info.path for info in closing.dropped}
        self._metadata.files = [info for info in self._metadata.files if info.path not in dropped]
        self.deleted_files = [*self.deleted_files, *(info.path for info in closing.dropped)]  # one atomic swap
        for info in closing.dropped:
            for name, count in info.topic_message_counts.items():
                self._deleted_counts[name] = self._deleted_counts.get(name, 0) + count
        if self._on_split is not None:
            self._on_split(str(closing.storage.path), str(closing.opened))

    def _detach_storage(self) -> tuple[_Storage, FileInfo, BagMetadata]:
        """Take the current file out of use: it, its metadata entry, and the metadata its close records."""
        storage = self._storage
        assert storage is not None
        self._storage = None
        entry = FileInfo.from_log_times(
            storage.path.name, self._file_first_ns, self._file_last_ns, self._file_counts
        )
        closing = dataclasses.replace(self._metadata, topics=list(self._metadata.topics),
                                      files=[*self._metadata.files, entry])
        self._file_counts = {}
        self._file_first_ns = self._file_last_ns = None
        return storage, entry, closing

    def _list_closed(self, storage: _Storage, info: FileInfo) -> OSError | None:
        """Record a closed file in the metadata (if readable); return the storage's error, if any."""
        with contextlib.suppress(OSError):
            self._closed_bytes += storage.path.stat().st_size
        if storage.readable:
            self._metadata.files.append(info)
        return storage.error

    def _close_storage(self) -> OSError | None:
        """Close the current file, record it in the metadata; return the storage's error, if any."""
        storage, _, closing = self._detach_storage()
        self._current_path = None
        return self._list_closed(storage, storage.close(closing.to_yaml()))

    def _fail(self, error: OSError) -> NoReturn:
        """The current file failed: finalize what reached it, then stop (see :meth:`_stop`)."""
        self._settle_closing(wait=True)  # the file split off before it is listed first
        assert self._storage is not None
        closed = self._storage.path
        self._close_storage()
        self._stop(error, closed)

    def _stop(self, error: OSError, closed: Path) -> NoReturn:
        """Record the failure, save ``metadata.yaml`` for the closed files and raise."""
        self._discard_prepared()
        action = "cannot write bag file"
        if closed.name not in {info.path for info in self._metadata.files}:
            action += " (it could not be finalized and is left out of metadata.yaml)"
        self._failure = self._error(error, action, closed)
        self._write_metadata_quietly()
        if self._on_split is not None:
            self._on_split(str(closed), "")
        raise self._failure from error

    def _write_metadata_quietly(self) -> None:
        # Used while a storage error is being reported: that error is the one the caller needs.
        with contextlib.suppress(OSError):
            self._metadata.write(self._path)

    def _error(self, error: OSError, action: str, path: Path | None = None) -> BagWriteError:
        reason = error.strerror or str(error)
        return BagWriteError(error.errno, f"{action}: {reason}", str(path or error.filename or self._path))
