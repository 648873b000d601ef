"""The bag reader: a rosbag2 bag (directory or single storage file) as connections and messages in time order.

It reads what rosbag2 has written since Foxy (``metadata.yaml`` versions 4 to 9, MCAP and SQLite3 in
all their schema versions, split bags, compression modes ``file`` and ``message``), what ``rosbags``
writes, and what this project's :class:`~baglib.write.writer.BagWriter` writes, including MCAP files a crash
left without summary (read up to their first damage). Each storage file is read by its storage
reader (:mod:`.mcap_reader`, :mod:`.sqlite_reader`, the interface in :mod:`.storage_reader`); this
module ties the files of a bag together: which topics there are (``metadata.yaml`` first, then what
the files say), decompression, and one stream of messages merged by log time across files.
"""
from __future__ import annotations

import heapq
import logging
import os
import shutil
import tempfile
import weakref
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from operator import attrgetter
from pathlib import Path, PurePath
from typing import Any, NamedTuple

import zstandard

from baglib.read.mcap_reader import McapReader
from baglib.format.metadata import METADATA_FILENAME, normalize_type
from baglib.read.metadata_read import StoredMetadata, load_metadata, parse_metadata
from baglib.read.sqlite_reader import SqliteReader
from baglib.read.storage_reader import BagReadError, ByteSource, StorageReader

__all__ = ["BagMessage", "BagReadError", "BagReader", "Connection"]

_log = logging.getLogger(__name__)

#: Storage id -> (reader, file extension).
_STORAGES: dict[str, tuple[type[McapReader] | type[SqliteReader], str]] = {
    McapReader.storage_id: (McapReader, ".mcap"),
    SqliteReader.storage_id: (SqliteReader, ".db3"),
}
_MAGICS = {b"\x89MCAP0\r\n": McapReader.storage_id, b"SQLite format 3\0": SqliteReader.storage_id}
_FILE_COMPRESSION_SUFFIX = ".zstd"  # rosbag2_compression's zstd file compression
_NO_END = 2**64


@dataclass(frozen=True)
class Connection:
    """A topic of the bag with the type it was recorded with.

    ``msgtype`` is ``pkg/msg/Type`` (also for bags that spelled it ``pkg/Type``);
    ``offered_qos_profiles`` are in :func:`.metadata.qos_profile_dict`'s (version 9) form whatever
    the bag's version, ``()`` when none were recorded; ``type_description_hash`` is ``""`` when
    absent; ``message_definition`` is ``(encoding, text)`` (e.g. ``("ros2msg", ...)``) when a storage
    file holds it, else ``None``.
    """

    id: int
    topic: str
    msgtype: str
    serialization_format: str
    offered_qos_profiles: tuple[dict[str, Any], ...]
    type_description_hash: str
    message_count: int
    message_definition: tuple[str, str] | None


class BagMessage(NamedTuple):
    """One message: ``data`` is the serialized message (decompressed), possibly a memoryview into a
    chunk; ``publish_time_ns`` equals ``log_time_ns`` where the storage keeps no publish time (SQLite3);
    ``file_index`` indexes :attr:`BagReader.files`."""

    connection: Connection
    log_time_ns: int
    publish_time_ns: int
    data: bytes | memoryview
    file_index: int


@dataclass
class _Topic:
    """A connection while the files are still being matched to it."""

    topic: str
    msgtype: str
    serialization_format: str
    offered_qos_profiles: tuple[dict[str, Any], ...]
    type_description_hash: str
    message_count: int
    message_definition: tuple[str, str] | None = None


class BagReader:
    """Read a bag: a directory with ``metadata.yaml``, or one ``.mcap`` / ``.db3`` file.

    Args:
        uri: the bag directory, or a single storage file (then everything is read from the file).
        storage_id: ``"mcap"`` or ``"sqlite3"`` to override what the metadata or file name says.
        source: a single MCAP file's bytes, read from elsewhere than ``uri`` (an object in a store, by range
            requests); ``uri`` then only names the file.

    Raises:
        BagReadError: no bag there (a directory with storage files but no ``metadata.yaml`` is named
            as an unfinished bag, with the ``bag recover`` command), an unsupported metadata version,
            storage id or compression, a listed file missing, a file that is not what it should be.

    Attributes: ``path``, ``storage_id``, ``files`` (the storage files as the bag lists them),
    ``ros_distro``, ``starting_time_ns`` / ``duration_ns`` / ``end_time_ns`` (earliest log time,
    latest minus earliest, latest; all 0 for a bag without messages), ``message_count``,
    ``connections`` (``connections[i].id == i``), ``custom_data``.
    """

    def __init__(self, uri: str | os.PathLike[str], storage_id: str = "", source: ByteSource | None = None) -> None:
        self.path = Path(uri)
        self._storages: list[StorageReader] = []
        self._temporary: Path | None = None
        self._cleanup: weakref.finalize | None = None
        self._message_compression = False
        self._closed = False
        if storage_id and storage_id not in _STORAGES:
            raise BagReadError(f"unknown storage id {storage_id!r} for {self.path} (this reader reads "
                               f"{', '.join(_STORAGES)})")
        try:
            if source is not None:
                self._open_file(storage_id, source)
            elif self.path.is_dir():
                self._open_directory(storage_id)
            elif self.path.is_file():
                self._open_file(storage_id)
            else:
                raise BagReadError(f"'{self.path}' does not exist")
        except BaseException:
            self.close()
            raise
        self._ranges = [storage.time_range() for storage in self._storages]

    # --- opening ----------------------------------------------------------------------------------

    def _open_directory(self, storage_id: str) -> None:
        metadata = load_metadata(self.path)
        source = str(self.path / METADATA_FILENAME)
        self.storage_id = storage_id or metadata.storage_identifier
        if self.storage_id not in _STORAGES:
            raise BagReadError(f"{source}: unknown storage id {self.storage_id!r} (this reader reads "
                               f"{', '.join(_STORAGES)})")
        mode = _compression_mode(metadata.compression_mode, metadata.compression_format, source)
        self._message_compression = mode == "message"
        self.files = [self._listed_file(name) for name in metadata.relative_file_paths]
        self._open_storages(file_compression=mode == "file")
        self.ros_distro = metadata.ros_distro or next(
            (storage.ros_distro for storage in self._storages if storage.ros_distro), "")
        self.custom_data = dict(metadata.custom_data)
        self.message_count = metadata.message_count
        self.starting_time_ns = metadata.starting_time_ns if metadata.message_count else 0
        self.duration_ns = metadata.duration_ns if metadata.message_count else 0
        topics = [_Topic(stored.name, _msgtype(stored.type), stored.serialization_format,
                         stored.offered_qos_profiles, stored.type_description_hash, stored.message_count)
                  for stored in metadata.topics]
        self._connect(topics, from_metadata=True)

    def _open_file(self, storage_id: str, source: ByteSource | None = None) -> None:
        name = self.path.name
        file_compression = name.endswith(_FILE_COMPRESSION_SUFFIX)
        if file_compression:
            name = name[:-len(_FILE_COMPRESSION_SUFFIX)]
        self.storage_id = storage_id or next(
            (storage for storage, (_, extension) in _STORAGES.items() if name.endswith(extension)), "")
        if not self.storage_id and not file_compression:
            if source is None:
                with open(self.path, "rb") as file:
                    start = file.read(16)
            else:
                start = source.pread(16, 0)
            self.storage_id = next((storage for magic, storage in _MAGICS.items() if start.startswith(magic)), "")
        if not self.storage_id:
            raise BagReadError(f"{self.path} is neither an MCAP nor an SQLite3 file (nor a bag directory)")
        self.files = [self.path]
        if source is None:
            self._open_storages(file_compression)
        elif self.storage_id == McapReader.storage_id and not file_compression:
            self._storages.append(McapReader(self.path, source))
        else:
            raise BagReadError(f"{self.path}: only an uncompressed MCAP file is read where it is stored")
        storage = self._storages[0]
        embedded = _embedded_metadata(storage)
        if embedded is not None:
            self._message_compression = _compression_mode(
                embedded.compression_mode, embedded.compression_format, str(self.path)) == "message"
        self.ros_distro = (embedded.ros_distro if embedded else "") or storage.ros_distro
        self.custom_data = dict(embedded.custom_data) if embedded else {}
        time_range = storage.time_range()
        self.starting_time_ns, self.duration_ns = (time_range[0], time_range[1] - time_range[0]) \
            if time_range else (0, 0)
        self._connect([], from_metadata=False)
        self.message_count = sum(connection.message_count for connection in self.connections)

    def _listed_file(self, name: str) -> Path:
        """A file ``metadata.yaml`` lists; rosbag2 (version 4, compressed) and version 3 bags prefixed
        the bag's directory name, so the bare file name is looked for too (as rosbag2 does)."""
        path = self.path / name
        if not path.is_file():
            bare = self.path / PurePath(name).name
            if not bare.is_file():
                raise BagReadError(f"{self.path / METADATA_FILENAME} lists {name}, which is not in {self.path}")
            path = bare
        return path

    def _open_storages(self, file_compression: bool) -> None:
        reader_class = _STORAGES[self.storage_id][0]
        for path in self.files:
            if file_compression:
                path = self._decompressed(path)
            self._storages.append(reader_class(path))

    def _decompressed(self, path: Path) -> Path:
        """The file ``X.db3.zstd`` decompressed to ``X.db3`` in a temporary directory (removed on close,
        or when the reader is collected)."""
        if self._temporary is None:
            self._temporary = Path(tempfile.mkdtemp(prefix="baglib-"))
            self._cleanup = weakref.finalize(self, shutil.rmtree, self._temporary, ignore_errors=True)
        target = self._temporary / (path.name.removesuffix(_FILE_COMPRESSION_SUFFIX) or "storage")
        try:
            with open(path, "rb") as source, open(target, "xb") as destination:
                zstandard.ZstdDecompressor().copy_stream(source, destination)
        except zstandard.ZstdError as error:
            raise BagReadError(f"{path} is not a zstd-compressed file: {error}") from error
        except OSError as error:
            raise BagReadError(f"cannot decompress {path} into {target}: {error.strerror}") from error
        return target

    def _connect(self, topics: list[_Topic], from_metadata: bool) -> None:
        """The connections: the given topics (from ``metadata.yaml``), then any topic only the files
        know (counted in the files). A file's topic belongs to the connection with its name and type;
        the connection takes the file's message definition, and QoS profiles and type hash where the
        metadata has none."""
        by_name_and_type = {(topic.topic, topic.msgtype): topic for topic in topics}
        counted: set[int] = set()  # the topics whose messages are counted in the files (by id())
        file_topics: list[dict[int, _Topic]] = []
        for file_index, storage in enumerate(self._storages):
            keys: dict[int, _Topic] = {}
            counts: dict[int, int] | None = None
            for stored in storage.topics:
                msgtype = _msgtype(stored.type)
                topic = by_name_and_type.get((stored.name, msgtype))
                if topic is None:
                    if from_metadata:
                        _log.warning("%s: topic %s (%s) is not in %s; reading it anyway",
                                     self.files[file_index], stored.name, msgtype, METADATA_FILENAME)
                    topic = by_name_and_type[stored.name, msgtype] = _Topic(
                        stored.name, msgtype, stored.serialization_format, stored.offered_qos_profiles,
                        stored.type_description_hash, 0)
                    topics.append(topic)
                    counted.add(id(topic))
                if id(topic) in counted:
                    counts = storage.message_counts() if counts is None else counts
                    topic.message_count += counts.get(stored.key, 0)
                topic.message_definition = topic.message_definition or stored.message_definition
                topic.offered_qos_profiles = topic.offered_qos_profiles or stored.offered_qos_profiles
                topic.type_description_hash = topic.type_description_hash or stored.type_description_hash
                keys[stored.key] = topic
            file_topics.append(keys)
        self.connections = [
            Connection(index, topic.topic, topic.msgtype, topic.serialization_format, topic.offered_qos_profiles,
                       topic.type_description_hash, topic.message_count, topic.message_definition)
            for index, topic in enumerate(topics)]
        connection_of = {id(topic): connection for topic, connection in zip(topics, self.connections, strict=True)}
        self._file_connections = [{key: connection_of[id(topic)] for key, topic in keys.items()}
                                  for keys in file_topics]

    # --- reading ----------------------------------------------------------------------------------

    @property
    def end_time_ns(self) -> int:
        """The latest log time (0 for a bag without messages)."""
        return self.starting_time_ns + self.duration_ns

    def messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None,
                 stop_ns: int | None = None) -> Iterator[BagMessage]:
        """The messages of ``topics`` (``None``: all) with ``start_ns <= log time < stop_ns``, in log-time
        order across all files; equal log times keep the bag's order (file order, then order in the
        file). Each call starts a new, independent pass (a player seeks by calling it again).
        """
        if self._closed:
            raise BagReadError(f"{self.path}: the reader is closed")
        names = None if topics is None else {topics} if isinstance(topics, str) else set(topics)
        low = -1 if start_ns is None else start_ns
        high = _NO_END if stop_ns is None else stop_ns
        runs: list[list[Iterator[BagMessage]]] = []
        run_end = -1
        for file_index, storage in enumerate(self._storages):
            time_range = self._ranges[file_index]
            connections = {key: connection for key, connection in self._file_connections[file_index].items()
                           if names is None or connection.topic in names}
            if time_range is None or not connections or time_range[1] < low or time_range[0] >= high:
                continue
            stream = self._file_messages(file_index, storage, connections, start_ns, stop_ns)
            if runs and time_range[0] < run_end:
                runs[-1].append(stream)  # overlaps the files before: merged with them
            else:
                runs.append([stream])
            run_end = max(run_end, time_range[1])
        for run in runs:
            if len(run) == 1:
                yield from run[0]
            else:  # heapq.merge keeps the order of its inputs for equal keys: file order
                yield from heapq.merge(*run, key=attrgetter("log_time_ns"))

    def _file_messages(self, file_index: int, storage: StorageReader, connections: dict[int, Connection],
                       start_ns: int | None, stop_ns: int | None) -> Iterator[BagMessage]:
        raw = storage.messages(list(connections), start_ns, stop_ns)
        if not self._message_compression:
            for key, log_time, publish_time, data in raw:
                yield BagMessage(connections[key], log_time, publish_time, data, file_index)
            return
        decompressor = zstandard.ZstdDecompressor()
        for key, log_time, publish_time, data in raw:
            try:
                data = decompressor.decompress(data)
            except zstandard.ZstdError:  # a frame without its content size
                try:
                    data = decompressor.decompressobj().decompress(data)
                except zstandard.ZstdError as error:
                    raise BagReadError(f"{self.files[file_index]}: a message of {connections[key].topic} at "
                                       f"{log_time} is not zstd-compressed: {error}") from error
            yield BagMessage(connections[key], log_time, publish_time, data, file_index)

    def close(self) -> None:
        """Close every file and remove the decompressed copies; idempotent."""
        self._closed = True
        storages, self._storages = self._storages, []
        for storage in storages:
            storage.close()
        if self._cleanup is not None:
            self._cleanup()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _msgtype(type_name: str) -> str:
    """``pkg/msg/Type``; a name that is no ROS type at all (an MCAP channel without schema) as it is."""
    try:
        return normalize_type(type_name)
    except ValueError:
        return type_name


def _compression_mode(mode: str, compression_format: str, source: str) -> str:
    """rosbag2_compression's mode as ``""``, ``"file"`` or ``"message"``; anything else is refused."""
    mode = mode.strip().lower()
    if mode in ("", "none"):
        return ""
    if mode not in ("file", "message"):
        raise BagReadError(f"{source}: unknown compression mode {mode!r}")
    if compression_format.strip().lower() != "zstd":
        raise BagReadError(f"{source}: compression format {compression_format!r} is not supported "
                           f"(this reader decompresses zstd)")
    return mode


def _embedded_metadata(storage: StorageReader) -> StoredMetadata | None:
    """The bag metadata a storage file keeps (rosbag2 since Humble), ``None`` if none is usable."""
    if not storage.serialized_metadata:
        return None
    try:
        return parse_metadata(storage.serialized_metadata, "the file's own metadata")
    except BagReadError:
        return None
