"""S4 of the recording benchmark (benchmarks/record/frames.py, compressed.py's targets): frames counted by stamp,
recorded messages decoded and matched to their raw frames by stamp for the PSNR, and the targets; on small made-up
frames and records (no container)."""
from __future__ import annotations

from typing import Any

import numpy as np
import simplejpeg
from builtin_interfaces.msg import Time
from foxglove_msgs.msg import CompressedVideo
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CompressedImage

from benchmarks.record.frames import camera_counts, decoded_frames, psnr, sample_stamps
from benchmarks.record.targets import Targets, s4_targets
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


def results(record: dict[str, Any]) -> list[str]:
    targets = Targets()
    s4_targets(record, targets)
    return [row["result"] for row in targets.rows]


def test_s4_targets() -> None:
    assert results(s4(5.0, 39.0, 4, 0)) == ["PASS", "PASS", "PASS"]
    assert results(s4(5.0, 39.0, 2, 0)) == ["FAIL", "PASS", "PASS"]        # too few cameras
    assert results(s4(5.0, 39.0, 2, 0, reached=False)) == ["N/A", "PASS", "PASS"]  # capped below: undecided
    assert results(s4(16.0, 39.0, 4, 0)) == ["FAIL", "PASS", "PASS"]       # too many bytes
    assert results(s4(5.0, 37.5, 4, 0)) == ["FAIL", "PASS", "PASS"]        # too low a PSNR
    assert results(s4(5.0, 39.0, 4, 1)) == ["PASS", "PASS", "FAIL"]        # raw lost a frame beside an encoder
