"""What the tools that copy messages from bags into a new bag share (``bag merge``, ``bag convert``): the checks
of their inputs and the description of each output topic.

* An unfinished input (no ``metadata.yaml``, a file it does not list, an MCAP file without footer, an SQLite3
  file with a journal left) is refused with the ``bag recover`` command, before anything is written.
* Types: the output describes each type once, with the first definition an input recorded for it (else the
  installed one), and every topic of that type carries the type description hash that goes with that
  definition: the hash recorded with it (empty for a bag of a rosbag2 older than Iron), or the installed type's
  when it is the installed definition. Readers that check the hash against the definition (rosbags) open it.
  A type neither recorded nor installed is described as rosbag2 describes it then, with
  :data:`~baglib.format.message_definitions.UNDESCRIBED`, and keeps the hash its topic recorded;
  :func:`undescribed` names those types, for the tool to warn (``bag convert``, as rosbag2) or refuse.
* A topic fed by several inputs offers the union of their QoS profiles, each once (as rosbag2's
  ``bag_rewrite`` gathers them).
"""
from __future__ import annotations

from collections.abc import Iterable

from baglib.format.bag_files import RECOVER_COMMAND, unfinished_files
from baglib.format.message_definitions import (
    UNDESCRIBED,
    MessageDefinitionNotFoundError,
    message_definition,
    type_hash_of_definition,
)
from baglib.format.metadata import TopicInfo
from baglib.read.reader import BagReader, Connection
from baglib.read.timeline import TopicSources

__all__ = ["BagCopyError", "TypeDescriptions", "refuse_unfinished", "topic_info", "type_descriptions", "undescribed"]

#: Per type: the definition the output describes it with (None: the installed one) and its type description hash.
TypeDescriptions = dict[str, tuple[tuple[str, str] | None, str]]


class BagCopyError(Exception):
    """The inputs cannot be copied into a new bag; the message says why."""


def refuse_unfinished(bags: Iterable[BagReader]) -> None:
    """BagCopyError naming the first unfinished bag and the command that recovers it."""
    for bag in bags:
        notes = unfinished_files(bag.path, {path.name for path in bag.files} if bag.path.is_dir() else None)
        if notes:
            raise BagCopyError(f"{bag.path} is unfinished ({'; '.join(notes)}). "
                               f"Run `{RECOVER_COMMAND} {bag.path}` first.")


def type_descriptions(topics: TopicSources) -> TypeDescriptions:
    """Per type of ``topics``: the definition and hash the output describes it with (see module doc)."""
    chosen: TypeDescriptions = {}
    for sources in topics.values():
        for _, connection in sources:
            msgtype, definition = connection.msgtype, connection.message_definition
            if definition and chosen.get(msgtype, (None, ""))[0] is None:
                chosen[msgtype] = (definition, type_hash_of_definition(msgtype, definition, connection.type_description_hash))
    for sources in topics.values():
        msgtype = sources[0][1].msgtype
        if msgtype not in chosen:
            try:
                message_definition(msgtype)
                chosen[msgtype] = (None, "")  # the writer describes it with the installed definition and hash
            except (MessageDefinitionNotFoundError, ValueError):
                chosen[msgtype] = (UNDESCRIBED, sources[0][1].type_description_hash)
    return chosen


def undescribed(topics: TopicSources, descriptions: TypeDescriptions) -> list[str]:
    """One sentence per type that :func:`type_descriptions` found neither recorded nor installed, naming its
    topics (their output names)."""
    names: dict[str, list[str]] = {}
    for name, sources in topics.items():
        if descriptions[sources[0][1].msgtype][0] == UNDESCRIBED:
            names.setdefault(sources[0][1].msgtype, []).append(name)
    return [f"no input records the definition of {msgtype} (topic {', '.join(topics_of)}) and it is not installed "
            f"here" for msgtype, topics_of in names.items()]


def topic_info(name: str, sources: list[tuple[int, Connection]], digest: str) -> TopicInfo:
    """The output topic: the first input's type, every input's QoS offers (each once), the type's hash."""
    first = sources[0][1]
    profiles: list[dict] = []
    for _, connection in sources:
        profiles += [dict(profile) for profile in connection.offered_qos_profiles if profile not in profiles]
    return TopicInfo(name, first.msgtype, first.serialization_format, profiles, digest)
