"""``ipc-component bag info``: what ``ros2 bag info`` prints, for users of the PyPI wheels (no ``ros2 bag``).

Like ``ros2 bag info`` it takes a bag directory or a single ``.mcap`` / ``.db3`` file. For a directory it reads
``metadata.yaml`` (versions 4 to 9, :mod:`baglib.read.metadata_read`) and the sizes of the files it lists; for a
file it reads what the file itself holds (its topics, counts and times, through the bag reader). It formats them
the way Kilted's rosbag2_py ``format_bag_meta_data`` does (Jazzy's is the same without actions, and says
``Service:`` where Kilted says ``Services:``): service event topics are listed as services, not as topics, and
their messages are not counted in ``Messages:``. An action's five topics (:mod:`baglib.format.action_topics`)
are listed as actions, each with its two topics and three services; an action recorded without its service
events (no action introspection where it ran) says so. A bag a crash left
unfinished (no ``metadata.yaml``, a file it does not list, an MCAP file without footer) is named as such, with
the command that repairs it.

Lyrical's options (rosbag2 #1804 and the verbose output of ``Info::print_output_verbose``): ``sort`` orders
topics, services and actions by name (the default), type or count (a service's event count, an action's
messages; with ``verbose`` requests plus responses, and an action's feedback and status messages);
``verbose`` reads every message once to add each topic's, service's and action's size contribution
(serialized bytes) and to count the requests and responses of each service and of each action's three services:
the distinct (client, sequence number) pairs among their request and response events, so a call seen by both
client and server counts once. Unlike rosbag2, which lists a service and an action once per file of a split bag
with that file's counts, each is listed once with the counts of the whole bag; and unlike Kilted, whose
non-verbose action lines give ``send_goal`` the ``get_result`` event count, each service gets its own.
``topic_names_only`` prints just the topic names.
"""
from __future__ import annotations

import datetime
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from baglib.read.metadata_read import StoredMetadata, StoredTopic, load_metadata
from baglib.read.reader import BagReader
from baglib.format.action_topics import SERVICE_INTERFACES, action_interface, action_name, \
    action_type, is_action_topic
from baglib.format import frame_accounts
from baglib.format.bag_files import RECOVER_COMMAND, unfinished_files
from baglib.format.service_events import (
    REQUEST_EVENTS,
    RESPONSE_EVENTS,
    event_info,
    is_service_event_topic,
    service_name,
    service_type,
)
from baglib.read.storage_reader import BagReadError

_LABEL_WIDTH = 19  # "Topic information: " and the padding of every other label
_SERVICE_LABEL_WIDTH = 21  # "Service information: ", which rosbag2 pads its service lines to
#: ``ros2 bag info --sort`` choices (rosbag2_py's InfoSortingMethod), the first the default
SORT_METHODS = ("name", "type", "count")


class BagInfoError(BagReadError):
    """The directory is not a readable rosbag2 bag."""


@dataclass
class BagSummary:
    """What ``bag info`` prints, from ``metadata.yaml`` or from a storage file itself."""

    files: list[str]
    size: int
    storage_id: str
    ros_distro: str
    starting_time_ns: int
    duration_ns: int
    message_count: int
    topics: list[StoredTopic]
    custom_data: dict[str, str] = field(default_factory=dict)


def listed_files(meta: StoredMetadata) -> list[str]:
    """The storage files ``metadata.yaml`` lists, as ``bag info`` names them."""
    return [info.path for info in meta.files] or meta.relative_file_paths


def directory_summary(meta: StoredMetadata, sizes: Mapping[str, int]) -> BagSummary:
    """A bag directory's summary from its ``metadata.yaml`` and the sizes of its files (name -> bytes; a file
    missing there is not counted), wherever the bag is: here, or in a store."""
    files = listed_files(meta)
    return BagSummary(files, sum(sizes.get(f, 0) for f in files), meta.storage_identifier, meta.ros_distro,
                      meta.starting_time_ns, meta.duration_ns, meta.message_count, meta.topics, meta.custom_data)


def file_summary(reader: BagReader, size: int) -> BagSummary:
    """A single storage file's summary from what the open ``reader`` of it found; ``size`` in bytes."""
    topics = [StoredTopic(c.topic, c.msgtype, c.serialization_format, c.offered_qos_profiles,
                          c.type_description_hash, c.message_count)
              for c in reader.connections]
    return BagSummary([reader.path.name], size, reader.storage_id, reader.ros_distro, reader.starting_time_ns,
                      reader.duration_ns, reader.message_count, topics)


def _directory_summary(bag_dir: Path) -> BagSummary:
    try:
        meta = load_metadata(bag_dir)
    except BagReadError as error:
        raise BagInfoError(str(error)) from error
    return directory_summary(meta, {f: (bag_dir / f).stat().st_size for f in listed_files(meta)
                                    if (bag_dir / f).exists()})


def _file_summary(path: Path) -> BagSummary:
    try:
        with BagReader(path) as reader:
            return file_summary(reader, path.stat().st_size)
    except BagReadError as error:
        raise BagInfoError(str(error)) from error


def _summary(path: Path) -> BagSummary:
    if path.is_file():
        return _file_summary(path)
    if not path.exists():
        raise BagInfoError(f"'{path}' does not exist")
    return _directory_summary(path)


def _file_size(size: int) -> str:
    units = ("B", "KiB", "MiB", "GiB", "TiB")
    value, exponent = float(size), 0
    while value >= 1024 and exponent < len(units) - 1:
        value, exponent = value / 1024, exponent + 1
    return f"{size} B" if exponent == 0 else f"{value:.1f} {units[exponent]}"


def _time(nanoseconds: int) -> str:
    moment = datetime.datetime.fromtimestamp(nanoseconds / 1e9)
    seconds, fraction = divmod(nanoseconds, 1_000_000_000)
    # rosbag2's "%b %e %Y": the day padded with a space, not a zero
    return f"{moment:%b} {moment.day:2d} {moment:%Y %H:%M:%S}.{fraction:09d} ({seconds}.{fraction:09d})"


def _block(label: str, lines: list[str], width: int = _LABEL_WIDTH) -> list[str]:
    pad = " " * width
    first = f"{label:<{width}}"
    return [first + (lines[0] if lines else "")] + [pad + line for line in lines[1:]]


@dataclass
class _Calls:
    """What ``verbose`` counts of one service (or an action's service): the distinct (client, sequence number)
    pairs among its request events and among its response events, as rosbag2_cpp's ``Info`` counts them."""

    requests: set[tuple[bytes, int]] = field(default_factory=set)
    responses: set[tuple[bytes, int]] = field(default_factory=set)

    @property
    def count(self) -> int:
        return len(self.requests) + len(self.responses)


@dataclass
class _Service:
    """A recorded service: its event topic's entry, and what ``verbose`` counts."""

    topic: StoredTopic
    calls: _Calls = field(default_factory=_Calls)

    @property
    def name(self) -> str:
        return service_name(self.topic.name)

    @property
    def type(self) -> str:
        return service_type(self.topic.type)


@dataclass
class _Action:
    """A recorded action: those of its five topics the bag holds (by interface), and what ``verbose`` counts of
    its three services."""

    name: str
    parts: dict[str, StoredTopic] = field(default_factory=dict)
    calls: dict[str, _Calls] = field(default_factory=lambda: {i: _Calls() for i in SERVICE_INTERFACES})

    @property
    def type(self) -> str:
        return next((t for t in (action_type(topic.type) for topic in self.parts.values()) if t), "unknown")

    def messages(self, interface: str) -> int:
        part = self.parts.get(interface)
        return part.message_count if part else 0

    def count(self, verbose: bool) -> int:
        """What ``--sort count`` orders actions by: their messages, or with ``verbose`` the feedback and status
        messages plus the services' requests and responses (rosbag2_py's ``generate_sorted_idx``)."""
        if verbose:
            return self.messages("feedback") + self.messages("status") + sum(c.count for c in self.calls.values())
        return sum(part.message_count for part in self.parts.values())


def _sorted(entries: Sequence[StoredTopic] | Sequence[_Service] | Sequence[_Action], sort: str,
            count: Callable[..., int]) -> list:
    """``entries`` ordered as rosbag2's ``generate_sorted_idx`` orders them (ties in bag order)."""
    if sort not in SORT_METHODS:
        raise BagInfoError(f"unknown sort method '{sort}': use one of {', '.join(SORT_METHODS)}")
    key = {"name": lambda e: e.name, "type": lambda e: e.type, "count": count}[sort]
    return sorted(entries, key=key)


def _read_calls(bag: Path, calls: dict[str, _Calls]) -> dict[str, int]:
    """Read every message once: the serialized bytes per topic, and the requests and responses of the services
    whose event topics ``calls`` names (services' and actions' alike)."""
    sizes: dict[str, int] = defaultdict(int)
    try:
        with BagReader(bag) as reader:
            for message in reader.messages():
                topic = message.connection.topic
                sizes[topic] += len(message.data)
                counted = calls.get(topic)
                if counted is None:
                    continue
                try:
                    kind, client, sequence = event_info(message.data)
                except ValueError as error:
                    raise BagInfoError(f"{topic} at {message.log_time_ns}: {error}") from None
                if kind in REQUEST_EVENTS:
                    counted.requests.add((client, sequence))
                elif kind in RESPONSE_EVENTS:
                    counted.responses.add((client, sequence))
    except BagReadError as error:
        raise BagInfoError(str(error)) from error
    return sizes


def _unfinished(bag_dir: Path, listed: list[str]) -> list[str]:
    """Warnings about storage files a crash left behind: unlisted ones, unfinished ones."""
    notes = unfinished_files(bag_dir, listed) if bag_dir.is_dir() else []
    if notes:
        notes.append(f"Run `{RECOVER_COMMAND} {bag_dir}` to make the whole bag readable.")
    return [f"Warning: {note}" for note in notes]


def _actions(actions: list[_Action], sizes: dict[str, int], verbose: bool) -> list[str]:
    """The ``Actions:`` part, as rosbag2 Kilted prints it (rosbag2_py's ``format_action_with_type``, and with
    ``verbose`` ``format_action_info``): every action with its two topics and three services, counted."""
    lines = [*_block("Actions:", [str(len(actions))]), "Action information:"]
    for action in actions:
        size = (f"Size Contribution: {_file_size(sum(sizes.get(t.name, 0) for t in action.parts.values()))} | "
                if verbose else "")
        formats = ", ".join(sorted({topic.serialization_format for topic in action.parts.values()}))
        lines.append(f"  Action: {action.name} | Type: {action.type} | Topics: 2 | Service: 3 | {size}"
                     f"Serialization Format: {formats}")
        lines += [f"    Topic: {topic} | Count: {action.messages(topic)}" for topic in ("feedback", "status")]
        for interface in SERVICE_INTERFACES:
            calls = action.calls[interface]
            lines.append(f"    Service: {interface} | Request Count: {len(calls.requests)} | "
                         f"Response Count: {len(calls.responses)}" if verbose else
                         f"    Service: {interface} | Event Count: {action.messages(interface)}")
        if not any(interface in action.parts for interface in SERVICE_INTERFACES):
            lines.append("    Note: no service events (no action introspection where it ran): its goals cannot "
                         "be replayed")
    return lines


def _frame_accounts(custom_data: dict[str, str]) -> list[str]:
    """Not in rosbag2: the raw frames of each topic recorded compressed, and how those not written were lost
    (baglib/format/frame_accounts.py)."""
    lines = []
    for topic, counts in sorted(frame_accounts.accounts(custom_data).items()):
        rest = {name: n for name, n in counts.items() if name not in ("received", "written")}
        lines.append(f"Frames: {topic} | Received: {counts.get('received', 0)} | Written: {counts.get('written', 0)}"
                     + "".join(f" | {name}: {n}" for name, n in rest.items()))
    return _block("Frame accounts:", lines) if lines else []


def format_bag_info(bag: str | Path, sort: str = "name", verbose: bool = False,
                    topic_names_only: bool = False, summary: BagSummary | None = None) -> str:
    """The ``ros2 bag info`` text for ``bag``: a bag directory (``metadata.yaml`` of any version from 4 to 9) or
    one storage file; ``sort``, ``verbose`` and ``topic_names_only`` as ``--sort``, ``--verbose`` and
    ``--topic-name`` (``verbose`` wins over ``topic_names_only``, as in rosbag2). ``summary``: what to print,
    read elsewhere (a bag in a store, :func:`directory_summary`, :func:`file_summary`); ``verbose`` then reads
    no messages, the caller refuses it."""
    bag = Path(bag)
    summary = summary or _summary(bag)
    actions: dict[str, _Action] = {}
    for topic in summary.topics:
        if is_action_topic(topic.name, topic.type):
            name = action_name(topic.name)
            actions.setdefault(name, _Action(name)).parts[action_interface(topic.name) or ""] = topic
    plain = [t for t in summary.topics if not is_action_topic(t.name, t.type)]
    topics = [t for t in plain if not is_service_event_topic(t.name, t.type)]
    services = {t.name: _Service(t) for t in plain if is_service_event_topic(t.name, t.type)}
    calls = {name: service.calls for name, service in services.items()}
    for action in actions.values():
        calls.update({action.parts[i].name: action.calls[i] for i in SERVICE_INTERFACES if i in action.parts})
    sizes = _read_calls(bag, calls) if verbose else {}
    by_count: Callable[..., int] = ((lambda s: s.calls.count) if verbose else (lambda s: s.topic.message_count))
    topics = _sorted(topics, sort, lambda t: t.message_count)
    listed = _sorted(list(services.values()), sort, by_count)
    if topic_names_only and not verbose:
        return "\n".join(topic.name for topic in topics)
    size = (lambda topic: f"Size Contribution: {_file_size(sizes.get(topic, 0))} | ") if verbose else (lambda _: "")
    topic_lines = [f"Topic: {t.name} | Type: {t.type} | Count: {t.message_count} | {size(t.name)}"
                   f"Serialization Format: {t.serialization_format}" for t in topics]
    if verbose:
        service_lines = [f"Service: {s.name} | Type: {s.type} | Request Count: {len(s.calls.requests)} | "
                         f"Response Count: {len(s.calls.responses)} | {size(s.topic.name)}"
                         f"Serialization Format: {s.topic.serialization_format}" for s in listed]
    else:
        service_lines = [f"Service: {s.name} | Type: {s.type} | Event Count: {s.topic.message_count} | "
                         f"Serialization Format: {s.topic.serialization_format}" for s in listed]
    start, duration = summary.starting_time_ns, summary.duration_ns
    service_messages = sum(service.topic.message_count for service in services.values()) + sum(
        topic.message_count for action in actions.values() for topic in action.parts.values())
    lines = [
        *_block("Files:", summary.files),
        *_block("Bag size:", [_file_size(summary.size)]),
        *_block("Storage id:", [summary.storage_id]),
        *_block("ROS Distro:", [summary.ros_distro or "unknown"]),
        *_block("Duration:", [f"{duration // 1_000_000_000}.{duration % 1_000_000_000:09d}s"]),
        *_block("Start:", [_time(start)]),
        *_block("End:", [_time(start + duration)]),
        *_block("Messages:", [str(summary.message_count - service_messages)]),
        *_block("Topic information:", topic_lines),
        *_block("Services:", [str(len(service_lines))]),
        *_block("Service information:", service_lines, _SERVICE_LABEL_WIDTH),
        *_actions(_sorted(list(actions.values()), sort, lambda a: a.count(verbose)), sizes, verbose),
        *_frame_accounts(summary.custom_data),
        *(_unfinished(bag, summary.files) if bag.is_dir() else []),
    ]
    return "\n".join(line.rstrip() for line in lines)
