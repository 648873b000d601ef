"""Reading a recorded bag back with rosbags (never trusting the recorder's counters) and counting, per topic,
what the drivers published in the measured window and what of it is in the bag.

Window membership is by ``header.stamp`` (capture time): T0 <= stamp <= T1. Images, point clouds and IMU
messages carry the driver's sequence number (Image and PointCloud2 ``data[0:8]``, Imu
``orientation_covariance[1]``); a gap in the recorded sequence numbers is a message published and lost.
"""
from __future__ import annotations

import struct
from pathlib import Path
from typing import Any, Callable, Optional

from benchmarks.record.scenarios import Scenario, TopicSpec

#: per topic, every message of the bag: (sequence number or None, stamp ns, serialized bytes)
Records = dict[str, list[tuple[Optional[int], int, int]]]


def sequence_reader(spec: TopicSpec, scenario: Scenario) -> Callable[[bytes], Optional[int]]:
    """Fast sequence-number extraction from CDR (checked against rosbags deserialization on first use)."""
    if spec.kind == "image":
        n = scenario.width * scenario.height * 3
        def image(raw: bytes) -> int:  # data is the last field
            assert struct.unpack_from("<I", raw, len(raw) - n - 4)[0] == n, "unexpected Image layout"
            return int.from_bytes(raw[len(raw) - n:len(raw) - n + 8], "little")
        return image
    if spec.kind == "cloud":
        n = 24 * scenario.lidar_points
        def cloud(raw: bytes) -> int:  # data, then is_dense (1 byte)
            assert struct.unpack_from("<I", raw, len(raw) - n - 5)[0] == n, "unexpected PointCloud2 layout"
            return int.from_bytes(raw[len(raw) - n - 1:len(raw) - n + 7], "little")
        return cloud
    if spec.kind == "imu":
        def imu(raw: bytes) -> int:  # header (stamp, frame_id), quaternion, orientation_covariance[0..8]
            frame_len = struct.unpack_from("<I", raw, 4 + 8)[0]
            offset = 8 + 4 + frame_len
            offset = (offset + 7) // 8 * 8 + 32 + 8
            return int(struct.unpack_from("<d", raw, 4 + offset)[0])
        return imu
    return lambda raw: None


def sequence_by_rosbags(typestore: Any, raw: bytes, spec: TopicSpec) -> Optional[int]:
    msg = typestore.deserialize_cdr(raw, spec.type_name)
    if spec.kind in ("image", "cloud"):
        return int.from_bytes(bytes(msg.data[:8]), "little")
    if spec.kind == "imu":
        return int(msg.orientation_covariance[1])
    return None


def read_bag(path: Path, scenario: Scenario, topics: dict[str, TopicSpec]) -> dict[str, Any]:
    """Every message of the bag (``records``), messages of other topics, and the metadata's message count."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    typestore = get_typestore(Stores.ROS2_JAZZY)
    readers = {name: sequence_reader(spec, scenario) for name, spec in topics.items()}
    checked: set[str] = set()
    records: Records = {name: [] for name in topics}
    unexpected = 0
    with Reader(path) as reader:
        for connection, _, raw in reader.messages():
            spec = topics.get(connection.topic)
            if spec is None:
                unexpected += 1
                continue
            assert raw[1] == 1, "only little-endian CDR is expected"
            sec, nanosec = struct.unpack_from("<iI", raw, 4)
            seq = readers[spec.name](raw)
            if spec.name not in checked:
                expected = sequence_by_rosbags(typestore, raw, spec)
                if expected != seq:
                    raise AssertionError(f"{spec.name}: sequence parser says {seq}, rosbags says {expected}")
                checked.add(spec.name)
            records[spec.name].append((seq, sec * 1_000_000_000 + nanosec, len(raw)))
        total = reader.message_count
    return {"records": records, "unexpected": unexpected, "metadata_count": total}


def published_in_window(recs: list[tuple[Optional[int], int, int]], t0: int, t1: int,
                        rate: float) -> tuple[int, bool]:
    """How many sequence numbers the driver published with a stamp in [t0, t1]; (count, estimated at an edge).

    Recorded messages count with their stamps. A gap in the sequence numbers is a lost message whose stamp is
    interpolated between the recorded neighbours. Before the first / after the last recorded message, lost
    messages are extrapolated at the nominal rate (then the count is marked estimated).
    """
    unique: dict[int, int] = {}
    for seq, stamp, _ in recs:
        unique.setdefault(seq, stamp)
    points = sorted(unique.items())
    if not points:
        return round((t1 - t0) / 1e9 * rate), True
    count = sum(1 for _, stamp in points if t0 <= stamp <= t1)
    for (a, ta), (b, tb) in zip(points, points[1:]):
        if b - a > 1 and tb >= t0 and ta <= t1:
            step = (tb - ta) / (b - a)
            count += sum(1 for k in range(1, b - a) if t0 <= ta + k * step <= t1)
    estimated = False
    first_stamp, last_stamp = points[0][1], points[-1][1]
    if first_stamp > t0:  # nothing recorded before the window: extrapolate back at the nominal rate
        count += int((min(first_stamp, t1) - t0) / 1e9 * rate)
        estimated = True
    if last_stamp < t1:  # nothing recorded after the window
        count += int((t1 - max(last_stamp, t0)) / 1e9 * rate)
        estimated = True
    return count, estimated


def window_counts(records: Records, topics: dict[str, TopicSpec], t0: int, t1: int) -> dict[str, dict[str, Any]]:
    """published / recorded / lost per topic over the window.

    CameraInfo has no sequence number: its published count is its image topic's (one CameraInfo per image,
    same stamp), its recorded count the CameraInfo messages stamped in the window.
    """
    window_s = (t1 - t0) / 1e9
    out: dict[str, dict[str, Any]] = {}
    for name, spec in topics.items():
        if spec.kind == "camera_info":
            continue
        recs = sorted(records.get(name, []))
        in_window = [r for r in recs if t0 <= r[1] <= t1]
        seqs = {r[0] for r in in_window}
        published, estimated = published_in_window(recs, t0, t1, spec.rate)
        out[name] = {"published": max(published, len(seqs)), "recorded": len(seqs),
                     "duplicates": len(in_window) - len(seqs), "bytes": sum(r[2] for r in in_window),
                     "estimated": estimated, "nominal": window_s * spec.rate}
    for name, spec in topics.items():
        if spec.kind != "camera_info":
            continue
        image = out[spec.image_topic]
        in_window = [r for r in records.get(name, []) if t0 <= r[1] <= t1]
        stamps = {r[1] for r in in_window}
        out[name] = {"published": image["published"], "recorded": len(stamps),
                     "duplicates": len(in_window) - len(stamps), "bytes": sum(r[2] for r in in_window),
                     "estimated": image["estimated"], "nominal": window_s * spec.rate}
    for entry in out.values():
        entry["lost"] = max(0, entry["published"] - entry["recorded"])
        entry["pub_ratio"] = entry["published"] / entry["nominal"] if entry["nominal"] else float("nan")
    return {name: out[name] for name in topics}
