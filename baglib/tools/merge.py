"""``ipc-component bag merge OUT BAG ...``: several bags into one, every message in log-time order.

The inputs are read as one :class:`~baglib.read.timeline.Timeline` (one message per input in memory) and
written with the project's :class:`~baglib.write.writer.BagWriter`, so the output is the same rosbag2 bag the
recorder writes (MCAP, or SQLite3) and memory does not grow with the inputs' size.

* Topics: a name and type found in several inputs is one topic of the output (its QoS offers are the union of
  the inputs'); a name with two types (or serialization formats, or type description hashes) is refused,
  naming both inputs. ``prefix_host`` keeps each input's topics apart under ``/<host>``: its ``ipc.host``
  (:mod:`baglib.format.fleet_keys`), else the input's own name; ``prefix_container`` under the full name of the
  container that recorded it (``ipc.container``, e.g. ``/front/container``), else the input's own name; both:
  ``/<host>/<container>``.
* Rigs are never mixed silently: a topic that inputs recorded by different containers (their ``ipc.host`` and
  ``ipc.container`` differ) would feed is refused, naming the topics, unless ``interleave`` names it (exact names
  or fnmatch patterns: a topic the containers share on purpose, as ``/tf``) or a prefix keeps them apart.
  :data:`NODE_TOPICS` are always one topic: every node publishes them, and each message names its node. An input
  that does not say which container recorded it (no ``ipc.container``) is merged by name.
* Types and unfinished inputs: as :mod:`baglib.tools.bag_copy` says.
* Clocks: ``align_clocks`` moves each input's log and publish times onto the commanding host's clock by its
  recorded ``ipc.clock_offset_ns`` (an input without one is refused); the messages' data are not touched.
* ``custom_data``: input ``n``'s keys are kept as ``input.<n>.<key>``, with ``input.<n>.path`` (its absolute
  path) and, when aligned, ``input.<n>.shift_ns`` (the offset taken off its times).
* A crashed input (no ``metadata.yaml``, a file it does not list, an MCAP file without footer, an SQLite3 file
  with a journal left) is refused with the ``bag recover`` command, before anything is written; a failure while
  merging removes the half-written output. Either way nothing is left at ``output``.
"""
from __future__ import annotations

import contextlib
import fnmatch
import os
import re
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from baglib.format import fleet_keys
from baglib.read.reader import BagReader, Connection
from baglib.read.storage_reader import BagReadError
from baglib.read.timeline import Timeline, TopicSources
from baglib.tools.bag_copy import BagCopyError, refuse_unfinished, topic_info, type_descriptions, undescribed
from baglib.write.writer import BagExistsError, BagWriter

__all__ = ["MergeError", "MergeReport", "NODE_TOPICS", "merge_bags"]

#: Topics every ROS node publishes, each message naming its node: interleaved whichever containers recorded them.
NODE_TOPICS = ("/rosout", "/parameter_events")


class MergeError(BagCopyError):
    """The inputs cannot be merged, or the output cannot be written; the message says why. Nothing is left at the
    output path."""


@dataclass
class MergeReport:
    """What a merge wrote."""

    output: Path
    inputs: int
    topics: int
    messages: int
    bytes_written: int
    seconds: float

    def text(self) -> str:
        return (f"Merged {self.inputs} bags into {self.output}: {self.messages} messages on {self.topics} topics, "
                f"{self.bytes_written / 1e6:.1f} MB in {self.seconds:.1f} s")


def merge_bags(output: str | os.PathLike[str], inputs: Sequence[str | os.PathLike[str]], storage_id: str = "mcap",
               align_clocks: bool = False, prefix_host: bool = False, prefix_container: bool = False,
               interleave: Sequence[str] = ()) -> MergeReport:
    """Merge ``inputs`` (bag directories or single storage files) into the new bag ``output`` (see module doc).

    Raises:
        MergeError: an input is unreadable or unfinished, the topics conflict, topics of different containers
            would be interleaved, a type has no definition, ``output`` exists or cannot be written.
    """
    started = time.monotonic()
    output = Path(output)
    if output.exists():
        raise MergeError(f"'{output}' already exists; choose a new output (bags are never overwritten)")
    try:
        timeline = Timeline(inputs, offset_of=_recorded_offset if align_clocks else None)
    except BagReadError as error:
        raise MergeError(f"cannot merge: {error}") from error
    with timeline:
        try:
            refuse_unfinished(timeline.bags)
        except BagCopyError as error:
            raise MergeError(f"cannot merge: {error}") from None
        if timeline.starting_time_ns < 0:
            raise MergeError("the clock offsets move messages before 1970: check the inputs' ipc.clock_offset_ns")
        prefixes = _prefixes(timeline, prefix_host, prefix_container)
        try:
            topics = timeline.topics(lambda index, connection: prefixes[index] + _plain_name(index, connection))
        except BagReadError as error:
            raise MergeError(f"cannot merge: {error}") from error
        _refuse_mixed_containers(timeline, topics, interleave)
        descriptions = type_descriptions(topics)
        missing = undescribed(topics, descriptions)
        if missing:
            raise MergeError(f"cannot merge: {missing[0]}")
        writer = _create(output, storage_id, _custom_data(timeline, align_clocks))
        try:
            for name, sources in topics.items():
                definition, digest = descriptions[sources[0][1].msgtype]
                writer.add_topic(topic_info(name, sources, digest), definition)
            written = _copy_messages(timeline, topics, writer)
            writer.close()
        except BaseException as error:
            with contextlib.suppress(Exception):
                writer.close()
            shutil.rmtree(output, ignore_errors=True)
            if isinstance(error, (OSError, ValueError, BagReadError)):
                raise MergeError(f"merge into {output} failed (nothing kept): {error}") from error
            raise
    return MergeReport(output, len(inputs), len(topics), written, writer.bytes_written, time.monotonic() - started)


def _recorded_offset(bag: BagReader) -> int:
    """The bag's ``ipc.clock_offset_ns``; BagReadError when it has none (it cannot be aligned)."""
    text = bag.custom_data.get(fleet_keys.CLOCK_OFFSET_NS, "")
    try:
        return int(text)
    except ValueError:
        raise BagReadError(f"{bag.path} has no clock offset to align ({fleet_keys.CLOCK_OFFSET_NS} is "
                           f"{text!r} in its custom_data); merge without --align-clocks") from None


def _plain_name(bag_index: int, connection: Connection) -> str:
    """The topic's own name, fully qualified (rosbag2 also stores names without the leading ``/``)."""
    return connection.topic if connection.topic.startswith("/") else "/" + connection.topic


def _token(text: str) -> str:
    """``text`` as one valid ROS name token."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", text) or "_"
    return "_" + token if token[0].isdigit() else token


def _prefixes(timeline: Timeline, by_host: bool, by_container: bool) -> list[str]:
    """Each input's prefix: ``/<host>`` and / or the container's full name (their fallback: the input's own name,
    once), or nothing."""
    prefixes = []
    for bag in timeline.bags:
        own = _token(bag.path.name if bag.path.is_dir() else bag.path.stem)
        host, container = bag.custom_data.get(fleet_keys.HOST), bag.custom_data.get(fleet_keys.CONTAINER)
        parts = [_token(host) if host else own] if by_host else []
        if by_container:
            if container:
                parts += [_token(part) for part in container.split("/") if part]
            elif own not in parts:
                parts.append(own)
        prefixes.append("".join("/" + part for part in parts))
    return prefixes


def _origin(bag: BagReader) -> str | None:
    """Which container recorded the bag (``host container``), from its fleet keys; None when it does not say."""
    container = bag.custom_data.get(fleet_keys.CONTAINER)
    return f"{bag.custom_data.get(fleet_keys.HOST) or '?'} {container}" if container else None


def _refuse_mixed_containers(timeline: Timeline, topics: TopicSources, interleave: Sequence[str]) -> None:
    """MergeError naming every output topic that inputs of different containers feed, unless it (or, prefixed,
    the inputs' own name of it) is one of :data:`NODE_TOPICS` or ``interleave`` names it."""
    origins = [_origin(bag) for bag in timeline.bags]
    mixed = {}
    for name, sources in topics.items():
        containers = sorted({origin for index, _ in sources if (origin := origins[index]) is not None})
        names = {name, *(_plain_name(index, connection) for index, connection in sources)}
        shared = any(fnmatch.fnmatchcase(each, pattern) for each in names for pattern in (*NODE_TOPICS, *interleave))
        if len(containers) > 1 and not shared:
            mixed[name] = containers
    if mixed:
        listed = "; ".join(f"{name} (from {', '.join(containers)})" for name, containers in sorted(mixed.items()))
        raise MergeError(f"cannot merge: topics of the same name were recorded by different containers and would be "
                         f"interleaved into one: {listed}. Add --prefix-container to keep each container's topics "
                         f"apart under its name, or --interleave TOPIC for a topic the containers share on purpose "
                         f"(e.g. /tf)")


def _custom_data(timeline: Timeline, align_clocks: bool) -> dict[str, str]:
    data = {}
    for index, bag in enumerate(timeline.bags):
        data[fleet_keys.input_key(index, "path")] = os.path.abspath(bag.path)
        if align_clocks:
            data[fleet_keys.input_key(index, "shift_ns")] = str(timeline.offsets_ns[index])
        data.update({fleet_keys.input_key(index, key): value for key, value in bag.custom_data.items()})
    return data


def _create(output: Path, storage_id: str, custom_data: dict[str, str]) -> BagWriter:
    try:
        return BagWriter(output, storage_id=storage_id, custom_data=custom_data)
    except BagExistsError:
        raise MergeError(f"'{output}' already exists; choose a new output (bags are never overwritten)") from None
    except (OSError, ValueError) as error:
        raise MergeError(f"cannot create {output}: {error}") from error


def _copy_messages(timeline: Timeline, topics: TopicSources, writer: BagWriter) -> int:
    """Write every message of the timeline to its output topic; the number written."""
    target = {id(connection): name for name, sources in topics.items() for _, connection in sources}
    written = 0
    for message in timeline.messages():
        writer.write(target[id(message.connection)], message.data, message.log_time_ns, message.publish_time_ns)
        written += 1
    return written
