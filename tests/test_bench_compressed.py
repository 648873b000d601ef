"""S4 of the recording benchmark (benchmarks/record/frames.py, compressed.py's targets): frames counted by stamp,
recorded messages decoded and matched to their raw frames by stamp for the PSNR, the codec limit, the ramp's
search for the largest lossless camera count, the targets and the comparison with the previous result; on small
made-up frames and records (no container, no timing asserted)."""
from __future__ import annotations

import argparse
import itertools
from pathlib import Path
from typing import Any, Callable

import numpy as np
import simplejpeg
from builtin_interfaces.msg import Time
from foxglove_msgs.msg import CompressedVideo
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CompressedImage

from benchmarks.record import compressed
from benchmarks.record.bench import Bench
from benchmarks.record.camera_search import largest_lossless, lossy_above, next_count, start_count
from benchmarks.record.codec_limit import codec_limit, frame_cost, measure_limits
from benchmarks.record.frames import camera_counts, decoded_frames, psnr, sample_stamps
from benchmarks.record.previous import compare_s4
from benchmarks.record.targets import S4_LIMIT_SHARE, Targets, s4_targets
from components.image_encoder.codecs import VideoCodec, choose

WIDTH, HEIGHT = 128, 96
MS = 1_000_000


def pictures(count: int) -> list[np.ndarray]:
    """A smooth picture panning by two pixels per frame, with a little noise."""
    rng = np.random.default_rng(1)
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH + 2 * count]
    scene = np.stack([x * 2, y * 2, 128 + 60 * np.sin(x / 7.0) * np.cos(y / 5.0)], axis=-1)
    return [np.clip(scene[:, 2 * i:2 * i + WIDTH] + rng.normal(0, 1, (HEIGHT, WIDTH, 3)), 0, 255).astype(np.uint8)
            for i in range(count)]


def stamp(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def test_frames_are_counted_by_stamp_against_the_camera_info_of_the_window() -> None:
    info = [(t * 33 * MS, 100) for t in range(10)]
    frames = [(t * 33 * MS, 5000) for t in (0, 1, 2, 4, 4, 5, 6, 7, 9)]  # 3 and 8 lost (skipped), 4 twice
    counts = camera_counts(info[:9] + [(11 * 33 * MS, 100)], frames, 33 * MS, 9 * 33 * MS, 30.0)
    # in [1, 9]: info of 1..8, frames of 1, 2, 4, 4, 5, 6, 7, 9
    assert counts["published"] == 9 and counts["recorded"] == 7 and counts["lost"] == 2
    assert counts["info_lost"] == 1 and counts["duplicates"] == 1
    assert counts["frame_bytes"] == 8 * 5000 and counts["info_bytes"] == 8 * 100
    assert abs(counts["pub_ratio"] - 9 / (8 * 0.033 * 30)) < 1e-9
    assert sample_stamps(frames, 0, 9 * 33 * MS, 4) == {0, 2 * 33 * MS, 5 * 33 * MS, 7 * 33 * MS}


def test_recorded_video_is_decoded_and_matched_to_the_raw_frames_by_stamp() -> None:
    raw = pictures(12)
    encoder = VideoCodec(choose("h264", "", -1, 0, 5), WIDTH, HEIGHT)
    messages = []
    for index, picture in enumerate(raw):
        for _, _, unit in encoder.encode(picture, "rgb8", keyframe=False):
            message = CompressedVideo(timestamp=stamp(1000 + index * 33 * MS), frame_id="cam", data=unit,
                                      format="h264")
            messages.append((1000 + index * 33 * MS, serialize_message(message)))
    by_stamp = {1000 + index * 33 * MS: picture for index, picture in enumerate(raw)}
    # the bag begins two frames after a keyframe: those before the next keyframe (frame 5) have no decoded frame
    decoded = dict(decoded_frames("h264", messages[2:], set(by_stamp)))
    assert sorted(decoded) == sorted(by_stamp)[5:]
    result = psnr(decoded, {s: by_stamp[s] for s in sorted(by_stamp)[2:]})
    assert result["frames"] == 7 and result["unmatched"] == 3
    assert 30 < result["psnr_min_db"] <= result["psnr_db"] < 60
    # a frame matched to the wrong stamp is far worse: the moving picture differs from frame to frame
    shifted = {s: by_stamp[s] for s in sorted(by_stamp)[6:]}
    wrong = {s: decoded[t] for s, t in zip(sorted(shifted), sorted(decoded))}
    assert psnr(wrong, shifted)["psnr_db"] < result["psnr_db"] - 5


def test_recorded_jpeg_is_decoded_by_stamp() -> None:
    raw = pictures(3)
    messages = [(index, serialize_message(CompressedImage(
        format="rgb8; jpeg compressed bgr8", data=simplejpeg.encode_jpeg(picture, 90, "RGB", "420"))))
        for index, picture in enumerate(raw)]
    decoded = dict(decoded_frames("jpeg", messages, {0, 2}))
    assert sorted(decoded) == [0, 2]
    assert psnr(decoded, {0: raw[0], 2: raw[2]})["psnr_db"] > 30


def s4(jpeg_pct: float, jpeg_db: float, jpeg_cameras: int, raw_lost: int, reached: bool = True) -> dict[str, Any]:
    def step(codec: str, cameras: int, pct: float, lossless: bool) -> dict[str, Any]:
        return {"codec": codec, "cameras": cameras, "raw_pct": pct, "lossless": lossless}

    def beside(codec: str, db: float) -> dict[str, Any]:
        return {"codec": codec, "psnr": {"psnr_db": db}, "info_lost": 0,
                "raw": {"lost": raw_lost, "published": 150, "min_pub_ratio": 1.0}}
    steps = [step("jpeg", n, jpeg_pct, n <= jpeg_cameras) for n in (1, 2, 4, 8) if n <= 2 * max(1, jpeg_cameras)]
    return {"codecs": ["jpeg", "h264"], "cap": 8, "steps": [*steps, step("h264", 1, 0.2, True)],
            "beside": [beside("jpeg", jpeg_db), beside("h264", 37.0)],
            "largest_lossless": {"jpeg": jpeg_cameras, "h264": 1}, "limit_reached": {"jpeg": reached, "h264": True}}


def results(record: dict[str, Any], rows: str = "codec") -> list[str]:
    """The results of S4's targets: the codec targets and raw beside them, or the codec limit targets."""
    targets = Targets()
    s4_targets(record, targets)
    limit_rows = [row for row in targets.rows if "codec limit" in row["target"]]
    return [row["result"] for row in (limit_rows if rows == "limit" else
                                      [row for row in targets.rows if row not in limit_rows])]


def test_s4_targets() -> None:
    assert results(s4(5.0, 39.0, 4, 0)) == ["PASS", "PASS", "PASS"]
    assert results(s4(5.0, 39.0, 2, 0)) == ["FAIL", "PASS", "PASS"]        # too few cameras
    assert results(s4(5.0, 39.0, 2, 0, reached=False)) == ["N/A", "PASS", "PASS"]  # capped below: undecided
    assert results(s4(16.0, 39.0, 4, 0)) == ["FAIL", "PASS", "PASS"]       # too many bytes
    assert results(s4(5.0, 37.5, 4, 0)) == ["FAIL", "PASS", "PASS"]        # too low a PSNR
    assert results(s4(5.0, 39.0, 4, 1)) == ["PASS", "PASS", "FAIL"]        # raw lost a frame beside an encoder


def with_limits(record: dict[str, Any], jpeg: float, h264: float = 1.0) -> dict[str, Any]:
    """``record`` with codec limits of ``jpeg`` and ``h264`` cameras (2 cores, 30 Hz)."""
    def limit(cameras: float) -> dict[str, Any]:
        return {"cameras": cameras, "ms_per_frame": 2 * 33.3 / cameras, "clock": "thread", "frames": 120}
    return {**record, "limits": {"cores": 2, "frame_interval_ms": 33.3, "frames": 120,
                                 "codecs": {"jpeg": limit(jpeg), "h264": limit(h264)}}}


def test_the_lossless_count_is_judged_against_the_codec_limit_of_the_same_run() -> None:
    assert results(with_limits(s4(5.0, 39.0, 4, 0), jpeg=4.7), "limit") == ["PASS", "PASS"]  # 4 >= 0.85 x 4.7
    assert results(with_limits(s4(5.0, 39.0, 4, 0), jpeg=4.8), "limit") == ["FAIL", "PASS"]  # 4 < 0.85 x 4.8
    capped = with_limits(s4(5.0, 39.0, 4, 0, reached=False), jpeg=8.0)
    assert results(capped, "limit") == ["N/A", "PASS"]                    # no loss up to the cap: undecided
    assert results(s4(5.0, 39.0, 4, 0), "limit") == ["N/A", "N/A"]       # no limit measured
    targets = Targets()
    s4_targets(with_limits(s4(5.0, 39.0, 4, 0), jpeg=4.7), targets)
    detail = next(row["detail"] for row in targets.rows if row["target"].startswith("S4 jpeg: lossless"))
    assert "85 % of the codec limit 4.70" in detail and "moonshot 6 camera(s): not yet" in detail


def test_the_codec_limit_is_cores_times_the_frame_interval_over_the_cpu_per_frame() -> None:
    assert abs(codec_limit(10.0, 30.0, 2) - 2 * 33.333 / 10.0) < 1e-3
    assert abs(codec_limit(5.0, 15.0, 4) - 4 * 66.667 / 5.0) < 1e-3


def test_the_cost_per_frame_runs_the_encoders_own_classes_on_photo_frames() -> None:
    jpeg = frame_cost("jpeg", "", 320, 240, 3)
    assert jpeg["encoder"] == "simplejpeg" and jpeg["quality"] == 90 and jpeg["frames"] == 3
    h264 = frame_cost("h264", "", 320, 240, 3)
    assert h264["encoder"] == "libx264" and h264["preset"] == "ultrafast"
    for cost in (jpeg, h264):
        assert 0 < cost["thread_ms_per_frame"] <= cost["process_ms_per_frame"]
        assert cost["ms_per_frame"] == cost[f"{cost['clock']}_ms_per_frame"]
    limits = measure_limits({"h264:superfast": ("h264", "superfast")}, 320, 240, 30.0, 2)
    limit = limits["codecs"]["h264:superfast"]
    assert limit["preset"] == "superfast" and limits["cores"] >= 1 and limits["frame_interval_ms"] == 1000 / 30
    assert abs(limit["cameras"] - codec_limit(limit["ms_per_frame"], 30.0, limits["cores"])) < 1e-9


def search(capacity: Callable[[int], bool], start: int, cap: int,
           kept: Callable[[int], float] | None = None) -> list[int]:
    """The camera counts the search runs against ``capacity`` (lossless or not per count), in order; ``kept``:
    the cameras' worth of frames a lossy run of that many cameras records."""
    outcomes: dict[int, bool] = {}
    worth: dict[int, float] = {}
    while (count := next_count(outcomes, start, cap, worth)) is not None:
        assert count not in outcomes and 1 <= count <= cap
        outcomes[count] = capacity(count)
        if kept is not None and not outcomes[count]:
            worth[count] = kept(count)
    return list(outcomes)


def test_the_search_brackets_the_largest_lossless_count_to_one_camera() -> None:
    for capacity, start, cap, error in itertools.product(range(0, 17), range(1, 17), (8, 16), (None, -2, 0, 3)):
        kept = None if error is None else (lambda n: max(0.0, capacity + error + 0.5))  # an estimate off by error
        runs = search(lambda n: n <= capacity, min(start, cap), cap, kept)
        outcomes = {n: n <= capacity for n in runs}
        assert largest_lossless(outcomes) == min(capacity, cap)
        assert lossy_above(outcomes) == (capacity + 1 if capacity < cap else None)
        assert len(runs) <= 2 + 2 * max(1, abs(min(capacity, cap) - start)).bit_length()
        if error == 0 and min(start, cap) > capacity:
            assert len(runs) <= 3  # a start above, an exact estimate: the start, the estimate, one above
    # near the estimate: two runs
    assert search(lambda n: n <= 6, 6, 16) == [6, 7]
    assert search(lambda n: n <= 6, 7, 16) == [7, 6]
    # far off, the steps double, then the gap is halved
    assert search(lambda n: n <= 3, 12, 16) == [12, 11, 9, 5, 1, 3, 4]
    assert search(lambda n: n <= 12, 2, 16) == [2, 3, 5, 9, 16, 12, 14, 13]
    assert search(lambda n: n <= 20, 8, 8) == [8]  # lossless at the cap (raw): done
    assert search(lambda n: False, 3, 16) == [3, 2, 1]  # nothing lossless: 0
    # a lossy run's cameras' worth of recorded frames is where the search goes next
    assert search(lambda n: n <= 8, 12, 16, lambda n: 8.4) == [12, 8, 9]
    assert search(lambda n: n <= 6, 12, 16, lambda n: 8.4) == [12, 8, 6, 7]  # an estimate too high: a run more
    # a noisy run below the answer does not hide it: the largest lossless count is bracketed from above
    runs = search(lambda n: n in (5, 6), 6, 16)
    assert runs == [6, 7] and largest_lossless({n: n in (5, 6) for n in runs}) == 6


def test_the_search_starts_at_the_target_share_of_the_codec_limit() -> None:
    assert start_count(7.06, S4_LIMIT_SHARE, 16) == 7    # 0.85 x 7.06 = 6.0: the smallest count reaching it
    assert start_count(5.0, S4_LIMIT_SHARE, 16) == 5
    assert start_count(40.0, S4_LIMIT_SHARE, 16) == 16   # within the cap
    assert start_count(0.3, S4_LIMIT_SHARE, 16) == 1
    assert start_count(None, S4_LIMIT_SHARE, 8) == 8     # raw: no limit, the cap


def test_each_codec_ramp_runs_the_searched_counts_from_its_limit(monkeypatch: Any, tmp_path: Path) -> None:
    capacity = {"jpeg": 9, "h264": 4, "raw": 8}
    ran: list[tuple[str, int]] = []

    def run(bench: Bench, scenario: Any, label: str, beside: bool = False) -> dict[str, Any]:
        ran.append((label, scenario.cameras))
        recorded = 150 * min(1.0, capacity[label] / scenario.cameras)
        return {"lossless": scenario.cameras <= capacity[label], "lost": 150 - recorded, "published": 150,
                "recorded": recorded, "min_pub_ratio": 1.0}
    monkeypatch.setattr(compressed, "run_compressed", run)
    args = argparse.Namespace(s4_max_cameras=16, s4_raw_cameras=8, s4_seconds=1.0, width=320, height=240, fps=30.0,
                              page_pause=0.0, quiet_wait=0.0, retries=0, retry_cpu=0.5)
    bench = Bench(args, tmp_path, node=None, log=lambda text: None)
    s4: dict[str, Any] = {"limits": {"codecs": {"jpeg": {"cameras": 12.0}, "h264": {"cameras": 5.5}}},
                          "caps": {}, "steps": [], "largest_lossless": {}, "limit_reached": {}}
    for label in ("raw", "jpeg", "h264"):
        compressed.ramp(bench, s4, label)
    assert ran == [("raw", 8), ("jpeg", 11), ("jpeg", 9), ("jpeg", 10), ("h264", 5), ("h264", 4)]
    assert s4["largest_lossless"] == capacity and s4["caps"] == {"raw": 8, "jpeg": 16, "h264": 16}
    assert s4["limit_reached"] == {"raw": False, "jpeg": True, "h264": True}
    assert [step["cameras"] for step in s4["steps"] if step["codec"] == "jpeg"] == [11, 9, 10]


def test_s4_is_compared_with_the_previous_result_per_codec() -> None:
    def record(jpeg: int, h264: int, h264_ms: float | None = None, capped: bool = False) -> dict[str, Any]:
        limits = {"codecs": {"h264": {"ms_per_frame": h264_ms}}} if h264_ms else {}
        return {"S4": {"largest_lossless": {"jpeg": jpeg, "h264": h264, "av1": 0}, "limits": limits,
                       "limit_reached": {"jpeg": not capped, "h264": True, "av1": True}}}
    changes = {c.name: c for c in compare_s4(record(8, 5, 10.0), record(9, 2))}
    assert set(changes) == {"jpeg cameras without loss", "h264 cameras without loss"}  # no cost then, av1 0 then
    assert changes["jpeg cameras without loss"].worse          # 8 of 9: more than the 10 % noise fewer
    assert not changes["h264 cameras without loss"].worse      # more cameras is better
    costs = {c.name: c for c in compare_s4(record(9, 5, 14.0), record(9, 5, 12.0))}
    assert costs["h264 codec CPU ms per frame"].worse and not costs["jpeg cameras without loss"].worse
    assert not compare_s4(record(9, 5, 11.0), record(9, 5, 12.0))[-1].worse
    # a ramp capped below the previous count without loss says nothing against it; above it, it is no worse
    assert [c.name for c in compare_s4(record(4, 5, capped=True), record(9, 5))] == ["h264 cameras without loss"]
    assert not compare_s4(record(12, 5, capped=True), record(9, 5))[0].worse
