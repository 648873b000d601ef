"""Several bags as one timeline: their messages merged by log time, streamed, as rosbag2 Kilted's player reads
the bags of ``ros2 bag play -i A -i B``.

rosbag2_transport's ``ReadersManager`` keeps each reader's next message and hands out the earliest; a tie goes
to the reader given first. The timeline does the same with :func:`heapq.merge` over each bag's own log-time
ordered stream (:meth:`.BagReader.messages`), which also keeps the input order for equal times, and holds one
message per bag in memory whatever the bags' sizes. Its start is the earliest start of any bag, its end the
latest end. Each bag may have a clock offset (its clock minus the timeline's): its log and publish times are
moved onto the timeline's clock (``t - offset``); the messages' data are left as they are.

The files of all bags are numbered in one sequence (:attr:`Timeline.files`, bag after bag), so that a message's
``file_index`` names its file whichever bag it comes from; :meth:`Timeline.bag_of_file` tells the bag.
"""
from __future__ import annotations

import heapq
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from operator import attrgetter
from pathlib import Path

from baglib.read.reader import BagMessage, BagReader, Connection
from baglib.read.storage_reader import BagReadError

__all__ = ["Timeline", "TopicSources"]

#: An output topic name -> the (bag index, connection) pairs that feed it, in input order.
TopicSources = dict[str, list[tuple[int, Connection]]]


class Timeline:
    """The bags ``uris`` (directories or single storage files) read as one stream of messages.

    Args:
        uris: the bags, in the order that breaks ties between equal log times.
        storage_ids: per bag, ``"mcap"``, ``"sqlite3"`` or ``""`` (detect); empty: detect for every bag.
        offset_of: a bag's clock minus the timeline's clock, from what the bag says about itself (its
            ``custom_data``); ``None``: every offset is 0.

    Raises:
        BagReadError: a bag cannot be opened (see :class:`.BagReader`), ``offset_of`` refuses one, or no bag is
            given; the bags opened before are closed again.

    Attributes: ``bags`` (the readers, in order), ``offsets_ns``, ``files`` (every bag's storage files, bag after
    bag), ``connections`` (every bag's, bag after bag; ``id`` is the index in its own bag), ``message_count``,
    ``starting_time_ns`` / ``end_time_ns`` / ``duration_ns`` on the timeline's clock (0 without messages).
    """

    def __init__(self, uris: Sequence[str | os.PathLike[str]], storage_ids: Sequence[str] = (),
                 offset_of: Callable[[BagReader], int] | None = None) -> None:
        if not uris:
            raise BagReadError("no bag to read")
        if len(storage_ids) not in (0, len(uris)):
            raise ValueError("storage_ids needs one entry per bag (or none)")
        self.bags: list[BagReader] = []
        try:
            for index, uri in enumerate(uris):
                self.bags.append(BagReader(uri, storage_ids[index] if storage_ids else ""))
            self.offsets_ns = [offset_of(bag) if offset_of else 0 for bag in self.bags]
        except BaseException:
            self.close()
            raise
        self.files: list[Path] = [path for bag in self.bags for path in bag.files]
        self._first_file = [0]
        for bag in self.bags:
            self._first_file.append(self._first_file[-1] + len(bag.files))
        self.connections: list[Connection] = [connection for bag in self.bags for connection in bag.connections]
        self.message_count = sum(bag.message_count for bag in self.bags)
        spans = [(bag.starting_time_ns - offset, bag.end_time_ns - offset)
                 for bag, offset in zip(self.bags, self.offsets_ns) if bag.message_count]
        self.starting_time_ns = min((start for start, _ in spans), default=0)
        self.end_time_ns = max((end for _, end in spans), default=0)
        self.duration_ns = self.end_time_ns - self.starting_time_ns

    @property
    def paths(self) -> list[Path]:
        return [bag.path for bag in self.bags]

    def file_range(self, bag_index: int) -> range:
        """The indexes in :attr:`files` of bag ``bag_index``'s files."""
        return range(self._first_file[bag_index], self._first_file[bag_index + 1])

    def bag_of_file(self, file_index: int) -> int:
        """The bag that file ``file_index`` of :attr:`files` belongs to."""
        return next(index for index in range(len(self.bags)) if file_index < self._first_file[index + 1])

    def topics(self, name: Callable[[int, Connection], str] = lambda _, connection: connection.topic
               ) -> TopicSources:
        """Every bag's connections grouped by the topic they go out on (``name(bag index, connection)``; default:
        their own name), in input order.

        Raises:
            BagReadError: one name is fed by connections of different types, serialization formats or (both
                known) type description hashes; the message names both bags.
        """
        grouped: TopicSources = {}
        for bag_index, bag in enumerate(self.bags):
            for connection in bag.connections:
                sources = grouped.setdefault(name(bag_index, connection), [])
                if sources:
                    self._check_same_type(sources[0], (bag_index, connection))
                sources.append((bag_index, connection))
        return grouped

    def _check_same_type(self, first: tuple[int, Connection], other: tuple[int, Connection]) -> None:
        (index_a, a), (index_b, b) = first, other
        for what, value_a, value_b in (("type", a.msgtype, b.msgtype),
                                       ("serialization format", a.serialization_format, b.serialization_format),
                                       ("type description hash", a.type_description_hash, b.type_description_hash)):
            if value_a != value_b and (what != "type description hash" or (value_a and value_b)):
                raise BagReadError(f"topic {b.topic} has {what} {value_b} in {self.bags[index_b].path} but {value_a} "
                                   f"in {self.bags[index_a].path}: the two cannot be one topic")

    def messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None,
                 stop_ns: int | None = None, windows: Sequence[tuple[int | None, int | None]] = ()
                 ) -> Iterator[BagMessage]:
        """The messages of ``topics`` (``None``: all) with ``start_ns <= log time < stop_ns`` on the timeline's
        clock, in log-time order across all bags; equal times in input order (bag, then the bag's own order).
        ``windows`` (one per bag, instead of ``start_ns`` and ``stop_ns``) gives each bag its own
        ``(start, stop)`` on the timeline's clock (``None``: open). Each call starts a new, independent pass."""
        if len(windows) not in (0, len(self.bags)) or (windows and (start_ns, stop_ns) != (None, None)):
            raise ValueError("windows needs one entry per bag, and no start_ns or stop_ns")
        names = None if topics is None else [topics] if isinstance(topics, str) else list(topics)
        windows = windows or [(start_ns, stop_ns)] * len(self.bags)
        streams = [self._bag_messages(index, names, *windows[index]) for index in range(len(self.bags))]
        try:
            if len(streams) == 1:
                yield from streams[0]
            else:  # heapq.merge keeps the order of its inputs for equal keys: input order
                yield from heapq.merge(*streams, key=attrgetter("log_time_ns"))
        finally:
            for stream in streams:
                stream.close()

    def _bag_messages(self, index: int, topics: list[str] | None, start_ns: int | None, stop_ns: int | None
                      ) -> Iterator[BagMessage]:
        offset, first_file = self.offsets_ns[index], self._first_file[index]
        stream = self.bags[index].messages(topics, None if start_ns is None else start_ns + offset,
                                           None if stop_ns is None else stop_ns + offset)
        if not offset and not first_file:
            return stream
        return (BagMessage(message.connection, message.log_time_ns - offset, message.publish_time_ns - offset,
                           message.data, message.file_index + first_file) for message in stream)

    def close(self) -> None:
        """Close every bag; idempotent."""
        bags, self.bags = self.bags, []
        for bag in bags:
            bag.close()

    def __enter__(self) -> Timeline:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
