"""``ipc-component bag merge OUT BAG ...``: several bags into one, every message in log-time order.

The inputs are read as one :class:`~baglib.read.timeline.Timeline` (one message per input in memory) and
written with the project's :class:`~baglib.write.writer.BagWriter`, so the output is the same rosbag2 bag the
recorder writes (MCAP, or SQLite3) and memory does not grow with the inputs' size.

* Topics: a name and type found in several inputs is one topic of the output (its QoS offers are the union of
  the inputs'); a name with two types (or serialization formats, or type description hashes) is refused,
  naming both inputs. ``prefix_host`` keeps each input's topics apart under ``/<host>``: its ``ipc.host``
  (:mod:`baglib.format.fleet_keys`), else the input's own name.
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
import os
import re
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from baglib.format import fleet_keys
from baglib.format.bag_files import RECOVER_COMMAND, unfinished_files
from baglib.format.message_definitions import MessageDefinitionNotFoundError, message_definition
from baglib.format.metadata import TopicInfo
from baglib.read.reader import BagReader, Connection
from baglib.read.storage_reader import BagReadError
from baglib.read.timeline import Timeline, TopicSources
from baglib.write.writer import BagExistsError, BagWriter

__all__ = ["MergeError", "MergeReport", "merge_bags"]


class MergeError(Exception):
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
               align_clocks: bool = False, prefix_host: bool = False) -> MergeReport:
    """Merge ``inputs`` (bag directories or single storage files) into the new bag ``output`` (see module doc).

    Raises:
        MergeError: an input is unreadable or unfinished, the topics conflict, a type has no definition,
            ``output`` exists or cannot be written.
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
        _refuse_unfinished(timeline)
        if timeline.starting_time_ns < 0:
            raise MergeError("the clock offsets move messages before 1970: check the inputs' ipc.clock_offset_ns")
        try:
            if prefix_host:
                prefixes = _host_prefixes(timeline)
                topics = timeline.topics(lambda index, connection: prefixes[index] + _plain_name(index, connection))
            else:
                topics = timeline.topics(_plain_name)
        except BagReadError as error:
            raise MergeError(f"cannot merge: {error}") from error
        definitions = {name: _definition(sources) for name, sources in topics.items()}
        writer = _create(output, storage_id, _custom_data(timeline, align_clocks))
        try:
            for name, sources in topics.items():
                writer.add_topic(_topic_info(name, sources), definitions[name])
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


def _refuse_unfinished(timeline: Timeline) -> None:
    for bag in timeline.bags:
        notes = unfinished_files(bag.path, {path.name for path in bag.files} if bag.path.is_dir() else None)
        if notes:
            raise MergeError(f"cannot merge {bag.path}: it is unfinished ({'; '.join(notes)}). "
                             f"Run `{RECOVER_COMMAND} {bag.path}` first.")


def _plain_name(bag_index: int, connection: Connection) -> str:
    """The topic's own name, fully qualified (rosbag2 also stores names without the leading ``/``)."""
    return connection.topic if connection.topic.startswith("/") else "/" + connection.topic


def _host_prefixes(timeline: Timeline) -> list[str]:
    """Each input's ``/<host>``: its ``ipc.host``, else its own name, as a valid ROS name token."""
    prefixes = []
    for bag in timeline.bags:
        host = bag.custom_data.get(fleet_keys.HOST) or (bag.path.name if bag.path.is_dir() else bag.path.stem)
        token = re.sub(r"[^A-Za-z0-9_]", "_", host) or "_"
        prefixes.append("/" + ("_" + token if token[0].isdigit() else token))
    return prefixes


def _definition(sources: list[tuple[int, Connection]]) -> tuple[str, str] | None:
    """The first definition an input recorded for the topic's type; else the installed one must exist."""
    recorded = next((connection.message_definition for _, connection in sources if connection.message_definition),
                    None)
    if recorded is None:
        msgtype = sources[0][1].msgtype
        try:
            message_definition(msgtype)
        except (MessageDefinitionNotFoundError, ValueError):
            raise MergeError(f"cannot merge: no input records the definition of {msgtype} (topic "
                             f"{sources[0][1].topic}) and it is not installed here") from None
    return recorded


def _topic_info(name: str, sources: list[tuple[int, Connection]]) -> TopicInfo:
    """The output topic: the first input's type, every input's QoS offers (each once), the first known hash."""
    first = sources[0][1]
    profiles: list[dict] = []
    for _, connection in sources:
        profiles += [dict(profile) for profile in connection.offered_qos_profiles if profile not in profiles]
    type_hash = next((connection.type_description_hash for _, connection in sources
                      if connection.type_description_hash), "")
    return TopicInfo(name, first.msgtype, first.serialization_format, profiles, type_hash)


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
