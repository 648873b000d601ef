"""What one storage file offers the bag reader: the small interface every storage reader implements.

Shaped like rosbags' storage plugins: a reader per storage (:mod:`.mcap_reader`, :mod:`.sqlite_reader`)
opens one file, says which topics it holds and what it knows about the bag, and yields its messages
in log-time order. Everything that concerns the bag as a whole (``metadata.yaml``, several files,
compression modes, connections) is :mod:`.reader`'s.
"""
from __future__ import annotations

from collections.abc import Collection, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

__all__ = ["BagReadError", "ByteSource", "FileTopic", "RawMessage", "StorageReader"]


class BagReadError(Exception):
    """A bag, its ``metadata.yaml`` or one of its storage files cannot be read; the message names the
    path and what is wrong with it."""


@dataclass(frozen=True)
class FileTopic:
    """A topic as one storage file describes it (an MCAP channel, a sqlite3 ``topics`` row).

    ``key`` is the file's own id for it (channel id, topic id); ``offered_qos_profiles`` are in
    :func:`.metadata.qos_profile_dict`'s form; ``message_definition`` is ``(encoding, text)`` or
    ``None`` when the file holds none.
    """

    key: int
    name: str
    type: str
    serialization_format: str
    offered_qos_profiles: tuple[dict[str, Any], ...]
    type_description_hash: str
    message_definition: tuple[str, str] | None


class ByteSource(Protocol):
    """A storage file's bytes read from elsewhere than a local file (an object in a store, by range requests):
    a seekable binary stream, which also reads at an offset without moving (``os.pread``'s order of
    arguments; thread-safe)."""

    def pread(self, length: int, offset: int) -> bytes: ...

    def seek(self, offset: int, whence: int = 0) -> int: ...

    def read(self, size: int = -1) -> bytes: ...


#: (topic key, log time, publish time, data); data may be a memoryview into a chunk.
RawMessage = tuple[int, int, int, "bytes | memoryview"]


class StorageReader(Protocol):
    """One open storage file."""

    topics: list[FileTopic]
    #: The ``metadata.yaml`` document the file embeds (without its wrapper), ``""`` when none.
    serialized_metadata: str
    #: What the file itself says about the ROS distribution that wrote it (``""``: nothing).
    ros_distro: str

    def time_range(self) -> tuple[int, int] | None:
        """Earliest and latest log time of the file's messages (``None``: it holds none)."""
        ...

    def message_counts(self) -> dict[int, int]:
        """Messages per topic key (may read the whole file: only for bags without ``metadata.yaml``)."""
        ...

    def messages(self, keys: Collection[int] | None, start_ns: int | None, stop_ns: int | None
                 ) -> Iterator[RawMessage]:
        """The messages of the topics ``keys`` (``None``: all) with ``start_ns <= log time < stop_ns``,
        in log-time order; equal log times keep their order in the file."""
        ...

    def close(self) -> None: ...
