"""The shape of a soak run: how long, how often each thing happens, the rig, and every component's load request.

The full run records the S1 rig (two 1920x1080 rgb8 cameras at 30 Hz with their CameraInfo, a LiDAR of 131072
points at 10 Hz, an IMU at 200 Hz: 405 MB/s) for ``--minutes``; the short run (``--short``, the test suite's) the
same rig with small frames, every period shortened, for 14 s.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from benchmarks.record.scenarios import Scenario

#: The extra driver's topics: the same for every instance, so a recorder that has them keeps them.
EXTRA_IMAGE_TOPIC = "/soak_extra/image_raw"
EXTRA_INFO_TOPIC = "/soak_extra/camera_info"
#: The player's topic, and the node names of the components the run loads.
REPLAY_TOPIC = "/soak_replay/chatter"
PLAYER = "soak_player"
IPC = {"use_intra_process_comms": True}


@dataclass(frozen=True)
class Component:
    """One load request: plugin, node name, parameters (dotted names), always intra-process."""

    plugin: str
    name: str
    parameters: dict[str, Any]

    def startup_entry(self) -> dict[str, Any]:
        """The entry of a ``--load`` start-up file."""
        return {"package": "components", "plugin": self.plugin, "name": self.name, "parameters": self.parameters,
                "extra_arguments": dict(IPC)}


@dataclass(frozen=True)
class SoakPlan:
    """What happens when, in seconds from the start of the churn."""

    seconds: float            # the churn's length
    split_s: float            # storage.max_bagfile_duration of every recorder
    extra_period_s: float     # an extra driver is loaded every ...
    extra_alive_s: float      # ... and unloaded this long after its load
    handover_period_s: float  # the recorder is handed over to a new one every ...
    warmup_s: float           # samples before this are left out of the fits and bounds
    rig: Scenario
    extra_width: int
    extra_height: int
    #: the player's bag: this many std_msgs/String "0", "1", ... at this rate, played in a loop
    replay_messages: int = 50
    replay_rate: float = 10.0
    #: storage.max_bag_files: circular recording keeps the disk use of a 405 MB/s rig bounded (the files are
    #: collected, and read, as soon as they are closed)
    max_bag_files: int = 2
    #: the container's --shutdown-timeout: a recorder stopped with a full stall reserve (up to 4 GiB) gets 80 %
    #: of it to write its backlog, more than the default 8 s at this machine's disk speed under the soak's load
    shutdown_timeout_s: float = 60.0

    def rig_topics(self) -> list[str]:
        return list(self.rig.topics())

    def recorded_topics(self) -> list[str]:
        return [*self.rig_topics(), EXTRA_IMAGE_TOPIC, EXTRA_INFO_TOPIC, REPLAY_TOPIC]

    def rig_components(self) -> list[dict[str, Any]]:
        """The rig drivers as ``--load`` entries (benchmarks.record.scenarios)."""
        return self.rig.components()

    def recorder(self, index: int, uri: Path) -> Component:
        """Recorder ``index``: every topic of the run into a bag of its own, split every ``split_s``, the default
        cache and stall reserve."""
        return Component("components::Recorder", f"soak_recorder_{index}",
                         {"record.topics": self.recorded_topics(), "storage.uri": str(uri),
                          "storage.max_bagfile_duration": float(self.split_s),
                          "storage.max_bag_files": self.max_bag_files})

    def extra(self, index: int) -> Component:
        """Extra driver ``index``: a camera on the shared extra topics, its instance named by frame_id."""
        return Component("components::CameraDriver", f"soak_extra_{index}",
                         {"width": self.extra_width, "height": self.extra_height, "fps": 30.0,
                          "topic": EXTRA_IMAGE_TOPIC, "frame_id": extra_frame_id(index)})

    def player(self, bag: Path) -> Component:
        """The player of the small bag, looping, paused until a recorder has subscribed to its topic."""
        return Component("components::Player", PLAYER, {"storage.uri": str(bag), "play.loop": True,
                                                        "play.start_paused": True})

    def summary(self) -> dict[str, Any]:
        fields = {key: value for key, value in asdict(self).items() if key != "rig"}
        return {**fields, "rig": self.rig.summary(), "recorded_topics": self.recorded_topics()}


def extra_frame_id(index: int) -> str:
    return f"extra{index}"


def full_plan(minutes: float) -> SoakPlan:
    """The S1 rig for ``minutes``: splits every 10 s, an extra driver every 5 s, a new recorder every minute; the
    first sixth (at most 5 minutes) is the warm-up."""
    seconds = 60.0 * minutes
    rig = Scenario("S1", "S1 multi-camera rig", seconds, cameras=2, width=1920, height=1080, fps=30.0,
                   lidar_points=131072, lidar_rate=10.0, imus=1, imu_rate=200.0)
    return SoakPlan(seconds=seconds, split_s=10.0, extra_period_s=5.0, extra_alive_s=2.5, handover_period_s=60.0,
                    warmup_s=min(300.0, seconds / 6), rig=rig, extra_width=640, extra_height=480)


def short_plan() -> SoakPlan:
    """14 s for the test suite: the rig's shape with 320x240 cameras and a 4096-point LiDAR, splits every 2 s,
    an extra driver every 2 s, a new recorder every 3.5 s (three in all); three files kept, so that a file stays
    listed for 4 s even on a busy machine."""
    seconds = 14.0
    rig = Scenario("S1", "S1 rig, small frames", seconds, cameras=2, width=320, height=240, fps=30.0,
                   lidar_points=4096, lidar_rate=10.0, imus=1, imu_rate=200.0)
    return SoakPlan(seconds=seconds, split_s=2.0, extra_period_s=2.0, extra_alive_s=1.0, handover_period_s=3.5,
                    warmup_s=3.0, rig=rig, extra_width=160, extra_height=120, max_bag_files=3)
