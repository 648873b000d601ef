"""Every message accounted for: the union of all the soak's bags against what was published.

Streams (topic, ``header.frame_id``) and what each must show in the union of the bags of every recorder:

* **rig drivers** (images, point cloud, IMU): every sequence number from the first one recorded to the last one
  recorded, no gap. The drivers start publishing before the first recorder is loaded, so their first numbers
  were never recorded (reported as ``before_first_recorder``); they are unloaded before the last recorder is
  stopped, so the last number recorded is the last one published unless the last recorder dropped it, which its
  counters would report (the run requires zero drops).
* **extra driver instances** (one camera loaded and unloaded every few seconds, all on the same topics, each
  with a frame_id of its own): every number from 0 to its last one recorded, except the first instance: its
  topics appear with it, so a recorder subscribes to them only when it discovers them (and from then on has them,
  and the next recorder is not handed over before it has them too): from its first number recorded.
* **CameraInfo** (rig and extra cameras): one per image, with the image's stamp: the same set of stamps as its
  image stream, from the later of the two streams' first stamps on.
* **the player's topic**: the bag's numbers 0 .. N-1 played in a loop. The same number recorded twice within
  half a loop (two recorders during a hand-over) is one publication; the publications in receive order must go
  0, 1, ..., N-1, 0, 1, ... without a skip, and there must be as many as the player says it published (at
  least one).

Duplicates inside one recorder's bag (the same number twice) count as errors; across recorders they are the
hand-over's overlap and expected.
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

from benchmarks.endurance.bag_files import FileContent
from benchmarks.endurance.message_fields import Stream
from benchmarks.endurance.plan import EXTRA_IMAGE_TOPIC, REPLAY_TOPIC, extra_frame_id

#: How many missing numbers a stream's report lists.
SHOWN = 10


def merged(runs: list[tuple[int, int]]) -> tuple[list[tuple[int, int]], int]:
    """``runs`` merged into disjoint sorted runs, and how many numbers two runs both held."""
    out: list[list[int]] = []
    overlap = 0
    for first, last in sorted(runs):
        if out and first <= out[-1][1] + 1:
            overlap += max(0, min(last, out[-1][1]) - first + 1)
            out[-1][1] = max(out[-1][1], last)
        else:
            out.append([first, last])
    return [(a, b) for a, b in out], overlap


def gaps(runs: list[tuple[int, int]], start: int) -> tuple[int, list[int]]:
    """How many numbers from ``start`` to the last run's end no run holds, and the first SHOWN of them."""
    count, shown, expected = 0, [], start
    for first, last in runs:
        if first > expected:
            count += first - expected
            shown.extend(range(expected, min(first, expected + SHOWN - len(shown))))
        expected = max(expected, last + 1)
    return count, shown


def camera_info_topic(image_topic: str) -> str:
    return image_topic.rpartition("/")[0] + "/camera_info"


@dataclass
class Union:
    """What the bags of all recorders hold, added file by file."""

    runs: dict[Stream, list[tuple[int, int]]] = field(default_factory=lambda: defaultdict(list))
    #: per recorder: its files' runs, to find a number recorded twice by one recorder
    recorder_runs: dict[int, dict[Stream, list[tuple[int, int]]]] = field(
        default_factory=lambda: defaultdict(lambda: defaultdict(list)))
    stamps: dict[Stream, set[int]] = field(default_factory=lambda: defaultdict(set))
    replay: list[tuple[int, int]] = field(default_factory=list)
    duplicates_in_files: int = 0

    def add(self, recorder: int, content: FileContent) -> None:
        for stream, runs in content.runs.items():
            self.runs[stream].extend(runs)
            self.recorder_runs[recorder][stream].extend(runs)
        for stream, stamps in content.stamps.items():
            self.stamps[stream].update(stamps)
        self.replay.extend(content.replay)
        self.duplicates_in_files += content.duplicates

    def duplicates_in_bags(self) -> int:
        """Numbers one recorder recorded twice (in two of its files, or twice in one)."""
        return self.duplicates_in_files + sum(merged(runs)[1] for streams in self.recorder_runs.values()
                                              for runs in streams.values())


def stream_report(runs: list[tuple[int, int]], from_zero: bool) -> dict[str, Any]:
    """First, last, distinct and missing numbers of one stream; ``from_zero``: numbers before the first recorded
    count as missing."""
    union, _ = merged(runs)
    if not union:
        return {"recorded": 0, "missing": 0, "missing_first": []}
    count, shown = gaps(union, 0 if from_zero else union[0][0])
    return {"first": union[0][0], "last": union[-1][1], "recorded": sum(b - a + 1 for a, b in union),
            "missing": count, "missing_first": shown}


def camera_info_report(union: Union, image: Stream) -> dict[str, Any]:
    """The CameraInfo stamps of a camera stream against its images' (module docstring)."""
    info = (camera_info_topic(image[0]), image[1])
    images, infos = union.stamps.get(image, set()), union.stamps.get(info, set())
    if not images or not infos:
        return {"images": len(images), "camera_infos": len(infos), "unmatched": len(images) + len(infos)}
    start = max(min(images), min(infos))
    images, infos = {s for s in images if s >= start}, {s for s in infos if s >= start}
    return {"images": len(images), "camera_infos": len(infos), "unmatched": len(images ^ infos)}


def replay_report(replay: list[tuple[int, int]], messages: int, loop_ns: int, published: int) -> dict[str, Any]:
    """The player's publications in the union against its count (module docstring)."""
    last_kept: dict[int, int] = {}
    order: list[int] = []
    for log_ns, number in sorted(replay):
        if number in last_kept and log_ns - last_kept[number] < loop_ns // 2:
            continue
        last_kept[number] = log_ns
        order.append(number)
    skips = sum(1 for a, b in zip(order, order[1:]) if b != (a + 1) % messages)
    if order and order[0] != 0:
        skips += 1
    return {"published": published, "recorded": len(order), "skips": skips,
            "missing": max(0, published - len(order)) + skips + (published == 0)}


def account(union: Union, rig_topics: list[str], extra_instances: int, replay_messages: int, loop_ns: int,
            replay_published: int) -> dict[str, Any]:
    """The whole accounting (module docstring): per stream, and ``lost``: every number missing, every stream
    (a rig topic, an extra instance) with nothing recorded at all, every unmatched CameraInfo stamp, every
    publication of the player missing."""
    rig = {}
    for topic in rig_topics:
        streams = sorted(stream for stream in union.runs if stream[0] == topic) or [(topic, "")]
        for stream in streams:
            entry = stream_report(union.runs.get(stream, []), from_zero=False)
            entry["before_first_recorder"] = entry.get("first")
            if topic.endswith("/image_raw"):
                entry["camera_info"] = camera_info_report(union, stream)
            rig[f"{topic} ({stream[1]})"] = entry
    extras = []
    for index in range(extra_instances):
        stream = (EXTRA_IMAGE_TOPIC, extra_frame_id(index))
        entry = stream_report(union.runs.get(stream, []), from_zero=index > 0)
        entry["camera_info"] = camera_info_report(union, stream)
        extras.append(entry)
    player = replay_report(union.replay, replay_messages, loop_ns, replay_published)
    entries = [*rig.values(), *extras]
    lost = (sum(e["missing"] + (e["recorded"] == 0) for e in entries) + player["missing"]
            + sum(e["camera_info"]["unmatched"] for e in entries if "camera_info" in e))
    return {"lost": lost, "duplicates_in_one_bag": union.duplicates_in_bags(), "rig": rig,
            "extra": {"instances": extra_instances, "recorded_messages": sum(e["recorded"] for e in extras),
                      "missing": sum(e["missing"] for e in extras),
                      "camera_info_unmatched": sum(e["camera_info"]["unmatched"] for e in extras),
                      "not_recorded": [i for i, e in enumerate(extras) if e["recorded"] == 0],
                      "with_missing": {i: e for i, e in enumerate(extras) if e["missing"]
                                       or e["camera_info"]["unmatched"]}},
            REPLAY_TOPIC: player}
