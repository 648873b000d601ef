"""``ipc-component bag convert``: rosbag2's ``bag_rewrite`` (``ros2 bag convert``) on this project's reader and
writer. Input bags (each with its own window of log times, rosbag2 Lyrical's ``--input-options``) are read as one
:class:`~baglib.read.timeline.Timeline`, merged by log time, and every message goes to each output bag whose
topic selection and time window take it (:mod:`baglib.tools.convert_options`). One pass, one message per input
and one chunk per MCAP file in memory, whatever the bags' sizes.

Only what is needed is read: the topics some output takes, and per input the log times its own window and the
outputs' windows together can reach. The MCAP reader finds those in the file's chunk index and reads only the
chunks that hold them (see :class:`~baglib.read.mcap_reader.McapReader`); a cut of the last tenth of a bag reads
about a tenth of it. SQLite3 files are read by their time index the same way.

Topic names are written fully qualified: rosbag2 stored a name as its node gave it (``chatter``), and the output
gets ``/chatter``, the topic it was published on, as ``bag merge`` does (the writer takes only full names).

Messages are copied as bytes, never decoded. A type whose definition no input records and that is not installed
here is converted as rosbag2's ``bag_rewrite`` converts it: its messages unchanged, the type described with an
empty definition (:mod:`baglib.tools.bag_copy`), and a warning naming the type and its topics in the report.

Refused before anything is written, naming what is wrong: an input that is missing, unreadable or unfinished
(with the ``bag recover`` command, :mod:`baglib.tools.bag_copy`), a topic of two types, a time window that holds
no message of its bag (or of the inputs, for an output), an output that selects no topic, an output that exists
or is named twice. A failure while writing removes every output of the run: nothing half-written is left.
"""
from __future__ import annotations

import contextlib
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from baglib.format.topic_selection import TopicSelection, absolute_name
from baglib.read.storage_reader import BagReadError
from baglib.read.timeline import Timeline, TopicSources
from baglib.tools.bag_copy import BagCopyError, refuse_unfinished, topic_info, type_descriptions, undescribed
from baglib.tools.convert_options import InputBag, OutputBag
from baglib.write.writer import BagWriter

__all__ = ["ConvertError", "ConvertReport", "convert_bags"]

_OPEN = (None, None)


class ConvertError(BagCopyError):
    """The conversion is refused or failed; the message says why. No output is left behind."""


@dataclass
class ConvertReport:
    """What a conversion wrote: per output bag, its path, topics and messages; the warnings, one sentence each."""

    outputs: list[tuple[Path, int, int]]
    inputs: int
    seconds: float
    warnings: list[str]

    def text(self) -> str:
        written = "; ".join(f"{path}: {messages} messages on {topics} topics"
                            for path, topics, messages in self.outputs)
        return f"Converted {self.inputs} bag(s) in {self.seconds:.1f} s: {written}"


def convert_bags(inputs: Sequence[InputBag], outputs: Sequence[OutputBag]) -> ConvertReport:
    """Convert ``inputs`` into ``outputs`` (see module doc).

    Raises:
        ConvertError: see module doc.
    """
    started = time.monotonic()
    if not inputs or not outputs:
        raise ConvertError("bag convert needs at least one input and one output bag")
    _check_outputs(outputs)
    try:
        timeline = Timeline([bag.uri for bag in inputs], [bag.storage_id for bag in inputs])
    except (BagReadError, ValueError) as error:
        raise ConvertError(f"cannot convert: {error}") from error
    with timeline:
        try:
            refuse_unfinished(timeline.bags)
            topics = timeline.topics(lambda _, connection: absolute_name(connection.topic))
        except (BagCopyError, BagReadError) as error:
            raise ConvertError(f"cannot convert: {error}") from None
        input_windows = [_input_window(index, bag, timeline) for index, bag in enumerate(inputs)]
        selected = [_selected(bag, topics) for bag in outputs]
        output_windows = [_output_window(bag, timeline, input_windows) for bag in outputs]
        taken = {name: topics[name] for chosen in selected for name in chosen}
        descriptions = type_descriptions(taken)
        warnings = [f"{sentence}: its messages are copied unchanged and the output records no definition for it, "
                    f"as ros2 bag convert does" for sentence in undescribed(taken, descriptions)]
        reach = _hull(output_windows)
        read_windows = [(_max(low, reach[0]), _min(high, reach[1])) for low, high in input_windows]
        writers: list[BagWriter] = []
        try:
            for bag, chosen in zip(outputs, selected):
                writers.append(_create(bag))
                for name in chosen:
                    definition, digest = descriptions[topics[name][0][1].msgtype]
                    writers[-1].add_topic(topic_info(name, topics[name], digest), definition)
            counts = _copy(timeline, topics, selected, output_windows, read_windows, writers)
            for writer in writers:
                writer.close()
        except BaseException as error:
            for writer in writers:
                with contextlib.suppress(Exception):
                    writer.close()
                shutil.rmtree(writer.path, ignore_errors=True)
            if isinstance(error, (OSError, ValueError, BagReadError)):
                raise ConvertError(f"bag convert failed (no output kept): {error}") from error
            raise
    written = [(writer.path, len(chosen), count) for writer, chosen, count in zip(writers, selected, counts)]
    return ConvertReport(written, len(inputs), time.monotonic() - started, warnings)


def _check_outputs(outputs: Sequence[OutputBag]) -> None:
    seen: set[Path] = set()
    for bag in outputs:
        path = Path(bag.uri).absolute()
        if path in seen:
            raise ConvertError(f"output bag {bag.uri} is named twice in output_bags")
        if path.exists():
            raise ConvertError(f"output bag {bag.uri} already exists; choose a new uri (bags are never overwritten)")
        seen.add(path)


def _window(bag: InputBag | OutputBag) -> tuple[int | None, int | None]:
    """The bag's window as ``[start, stop)`` (rosbag2's end is included); ``None``: open."""
    return (bag.start_time_ns if bag.start_time_ns >= 0 else None,
            bag.end_time_ns + 1 if bag.end_time_ns >= 0 else None)


def _overlaps(window: tuple[int | None, int | None], first: int, last: int) -> bool:
    return (window[0] is None or window[0] <= last) and (window[1] is None or window[1] > first)


def _shown(bag: InputBag | OutputBag) -> str:
    ends = [str(value) if value >= 0 else "open" for value in (bag.start_time_ns, bag.end_time_ns)]
    return f"[{ends[0]}, {ends[1]}]"


def _input_window(index: int, bag: InputBag, timeline: Timeline) -> tuple[int | None, int | None]:
    window = _window(bag)
    reader = timeline.bags[index]
    if window != _OPEN and not (reader.message_count and _overlaps(window, reader.starting_time_ns,
                                                                   reader.end_time_ns)):
        raise ConvertError(f"input bag {bag.uri}: the time window {_shown(bag)} holds no message of the bag (its "
                           f"messages are logged from {reader.starting_time_ns} to {reader.end_time_ns} ns)")
    return window


def _output_window(bag: OutputBag, timeline: Timeline, input_windows: list[tuple[int | None, int | None]]
                   ) -> tuple[int | None, int | None]:
    window = _window(bag)
    spans = [(_max(low, reader.starting_time_ns), _min(high, reader.end_time_ns + 1))
             for reader, (low, high) in zip(timeline.bags, input_windows) if reader.message_count]
    if window != _OPEN and not any(_overlaps(window, first, stop - 1) for first, stop in spans):
        read = f"they are read from {min(first for first, _ in spans)} to {max(stop for _, stop in spans) - 1} ns" \
            if spans else "they hold none"
        raise ConvertError(f"output bag {bag.uri}: the time window {_shown(bag)} holds no message of the inputs "
                           f"({read})")
    return window


def _selected(bag: OutputBag, topics: TopicSources) -> list[str]:
    """The input topics the output takes, in input order; ConvertError when none."""
    try:
        selection = TopicSelection(bag)
    except Exception as error:  # re.error: not a regular expression
        raise ConvertError(f"output bag {bag.uri}: {error}") from None
    chosen = [name for name, sources in topics.items() if selection.selects(name, sources[0][1].msgtype)]
    if not chosen:
        raise ConvertError(f"output bag {bag.uri} selects none of the inputs' {len(topics)} topics: give it "
                           f"all_topics: true, topics, topic_types, regex, all_services, services, "
                           f"all_actions or actions")
    return chosen


def _hull(windows: list[tuple[int | None, int | None]]) -> tuple[int | None, int | None]:
    """The smallest window that holds all ``windows``."""
    starts, stops = [low for low, _ in windows], [high for _, high in windows]
    return (None if None in starts else min(starts), None if None in stops else max(stops))  # type: ignore[type-var]


def _max(a: int | None, b: int | None) -> int | None:
    return b if a is None else a if b is None else max(a, b)


def _min(a: int | None, b: int | None) -> int | None:
    return b if a is None else a if b is None else min(a, b)


def _create(bag: OutputBag) -> BagWriter:
    return BagWriter(bag.uri, storage_id=bag.storage_id, max_bagfile_size=bag.max_bagfile_size,
                     max_bagfile_duration=bag.max_bagfile_duration, storage_preset_profile=bag.storage_preset_profile,
                     custom_data=bag.custom_data)


def _copy(timeline: Timeline, topics: TopicSources, selected: list[list[str]],
          output_windows: list[tuple[int | None, int | None]], read_windows: list[tuple[int | None, int | None]],
          writers: list[BagWriter]) -> list[int]:
    """Write each message read to every output that takes it; the messages written per output."""
    routes: dict[int, list[tuple[int, str, int, int]]] = {}  # id(connection) -> (output, name, start, stop)
    for output, chosen in enumerate(selected):
        low, high = output_windows[output]
        for name in chosen:
            for _, connection in topics[name]:
                routes.setdefault(id(connection), []).append(
                    (output, name, -1 if low is None else low, 2**64 if high is None else high))
    stored = sorted({connection.topic for chosen in selected for name in chosen for _, connection in topics[name]})
    counts = [0] * len(writers)
    for message in timeline.messages(stored, windows=read_windows):
        for output, name, low, high in routes[id(message.connection)]:
            if low <= message.log_time_ns < high:
                writers[output].write(name, message.data, message.log_time_ns, message.publish_time_ns)
                counts[output] += 1
    return counts
