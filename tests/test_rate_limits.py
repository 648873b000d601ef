"""``record.max_rates``: per-topic rate limits leave messages out of a bag by design, counted apart from losses.

The limiter's choice is checked on made-up receive times; the recorder's on real drivers delivering
intra-process in an in-process container, with the bag read back by rosbags (rates from the bag's own stamps,
never from the wall clock of the test).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml
from rosbags.rosbag2 import Reader

from component_container.component_manager import ComponentConstructionError
from component_container.startup_file import load_request
from components.recorder.rate_limits import RateLimiter, parse_max_rates
from ipc_testing import in_process_manager, wait_until

IMU = "/imu/imu"
IMAGE = "/camera/image_raw"
CAMERA_INFO = "/camera/camera_info"


def kept_times(limiter: RateLimiter, topic: str, times_ns: list[int]) -> list[int]:
    return [t for t in times_ns if limiter.admits(topic, t)]


def test_a_limit_keeps_the_configured_rate_whatever_the_jitter_and_makes_no_burst_after_a_pause() -> None:
    limiter = RateLimiter(parse_max_rates(["/cam.*/image_raw:5", "/lidar:2"]))
    frames = [round(n * 1e9 / 30 + (n * 7919 % 11 - 5) * 1e6) for n in range(300)]  # 10 s at 30 Hz, +-5 ms
    kept = kept_times(limiter, "/cam0/image_raw", frames)
    assert len(kept) == 50, len(kept)
    assert all(b - a >= 0.19e9 for a, b in zip(kept, kept[1:]))
    after_pause = [frames[-1] + 5_000_000_000 + round(n * 1e9 / 30) for n in range(30)]  # 5 s later, 1 s
    assert len(kept_times(limiter, "/cam0/image_raw", after_pause)) == 5, "a pause was made up by a burst"
    assert limiter.left_out() == {"/cam0/image_raw": 330 - 55}
    assert kept_times(limiter, "/imu", frames) == frames, "a topic no pattern matches is limited"
    assert len(kept_times(limiter, "/lidar", frames)) == 20
    assert len(kept_times(limiter, "/lidar/points", frames)) == 300, "a pattern matched part of a name"


@pytest.mark.parametrize("entry, complaint", [
    ("/lidar", "must be 'TOPIC_OR_REGEX:RATE'"),
    (":5", "must be 'TOPIC_OR_REGEX:RATE'"),
    ("/lidar:fast", "is not a number"),
    ("/lidar:0", "must be in"),
    ("/lidar:-2", "must be in"),
    ("/cam[:5", "not a valid regular expression"),
])
def test_bad_max_rates_entries_are_load_errors_naming_the_parameter(tmp_path: Path, entry: str,
                                                                    complaint: str) -> None:
    with in_process_manager("rate_limits_bad", allow_module_plugins=True) as manager:
        with pytest.raises(ComponentConstructionError) as error:
            manager.load(load_request({"package": "components", "plugin": "components::Recorder",
                                       "parameters": {"storage.uri": str(tmp_path / "bag"),
                                                      "record.max_rates": [entry]}}, 1))
        assert "'record.max_rates'" in str(error.value) and complaint in str(error.value), error.value


def bag_log_times(bag: Path) -> dict[str, list[int]]:
    """Per topic, the log time stamps of its messages, as rosbags reads them."""
    times: dict[str, list[int]] = {}
    with Reader(bag) as reader:
        for connection, timestamp, _ in reader.messages():
            times.setdefault(connection.topic, []).append(timestamp)
    return times


def test_the_recorder_keeps_each_limited_topic_at_its_rate_and_counts_the_rest_by_design(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    limits = [f"{IMU}:20", "/cam.*/image_raw:5"]
    with in_process_manager("rate_limits_test", use_intra_process_comms=True,
                            allow_module_plugins=True) as manager:
        def load(plugin: str, **parameters: Any) -> Any:
            return manager.load(load_request({"package": "components", "plugin": plugin,
                                              "parameters": parameters}, 1))

        load("components::ImuDriver", rate=200.0)
        load("components::CameraDriver", width=64, height=48, fps=30.0)
        recorder = load("components::Recorder", **{"storage.uri": str(bag), "record.max_rates": limits,
                                                   "record.topics": [IMU, IMAGE, CAMERA_INFO]}).node

        def current(topic: str, count: str) -> int:
            return recorder.stats()["current"]["topics"].get(topic, {}).get(count, 0)

        assert wait_until(lambda: current(IMAGE, "written") >= 15 and current(IMU, "written") >= 60, 30.0)
        assert recorder._session.drop_reasons() == {}, "rate-limited messages reported as lost"
        final = recorder.stop_recording()

    topics = final["topics"]
    times = bag_log_times(bag)
    for topic, rate in ((IMU, 20.0), (IMAGE, 5.0)):
        counts, stamps = topics[topic], times[topic]
        assert counts["dropped"] == 0 and counts["rate_limited"] > 0, counts
        assert counts["received"] == counts["written"] + counts["rate_limited"], counts
        assert len(stamps) == counts["written"]
        measured = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9)
        # Never above the limit (kept messages are at least one period apart on average, by construction);
        # below it only when the driver itself fell behind on this shared machine.
        assert 0.7 * rate <= measured <= rate * 1.001, (topic, measured)
        assert final["dropped_by_design"][topic] == {"rate_limited": counts["rate_limited"]}
    info = topics[CAMERA_INFO]
    assert info["rate_limited"] == 0 and info["written"] == info["received"] == len(times[CAMERA_INFO])
    assert info["written"] > 2 * topics[IMAGE]["written"], "camera_info was limited with the images"
    assert final["drop_reasons"] == {}, "rate-limited messages reported as drops"
    metadata = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["custom_data"]["record.max_rates"] == ", ".join(limits)
