"""The scenarios: which drivers run, at what rates, and the topics they publish.

* S1, a multi-camera rig: cameras (default two 1920x1080 rgb8 at 30 Hz), a LiDAR and one IMU;
* S2, a ramp: 1080p cameras added one at a time (on top of the S1 LiDAR and IMU unless ``--s2-base cameras``);
* S3, an IMU storm: many IMU topics at a high rate (default ten at 1 kHz): per-message cost, not bytes;
* S4, compressed recording: 1080p cameras with photographic content (``content:=photo``) recorded raw or
  compressed (benchmarks/record/compressed.py).
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

#: The recorder modes: ipc, ipc splitting its files every --split-mb MiB, and dds.
RECORDER_MODES = ("ipc", "split", "dds")
IPC_MODES = ("ipc", "split")  # the modes that record in the drivers' process
#: A driver that published less than this share of its nominal rate did not keep up.
PUBLISH_RATE_OK = 0.97


@dataclass
class TopicSpec:
    name: str
    type_name: str
    kind: str  # image | camera_info | cloud | imu
    rate: float
    size: int = 0  # serialized CDR bytes of one message
    image_topic: str = ""  # camera_info: its image topic


@dataclass
class Scenario:
    key: str
    title: str
    seconds: float
    cameras: int = 0
    width: int = 1920
    height: int = 1080
    fps: float = 30.0
    lidar_points: int = 0  # 0: no lidar
    lidar_rate: float = 10.0
    imus: int = 0
    imu_rate: float = 200.0
    content: str = "random"  # the cameras' content: random bytes or "photo"

    def describe(self) -> str:
        parts = []
        if self.cameras:
            parts.append(f"{self.cameras}x camera {self.width}x{self.height} rgb8 @ {self.fps:g} Hz"
                         + (f", {self.content} content" if self.content != "random" else ""))
        if self.lidar_points:
            parts.append(f"lidar {self.lidar_points} pts @ {self.lidar_rate:g} Hz")
        if self.imus:
            parts.append(f"{self.imus}x IMU @ {self.imu_rate:g} Hz")
        return ", ".join(parts) + f"; {self.seconds:g} s window"

    def summary(self) -> dict[str, Any]:
        """What a result file says about the scenario: its description, window and nominal data rate."""
        topics = self.topics().values()
        return {"key": self.key, "title": self.title, "describe": self.describe(), "seconds": self.seconds,
                "cameras": self.cameras, "nominal_mb_per_s": sum(t.size * t.rate for t in topics) / 1e6,
                "nominal_messages_per_s": sum(t.rate for t in topics)}

    def components(self) -> list[dict[str, Any]]:
        """The drivers as entries of a ``--load`` start-up file, every one intra-process."""
        ipc = {"use_intra_process_comms": True}
        out: list[dict[str, Any]] = []
        for i in range(self.cameras):
            out.append({"package": "components", "plugin": "components::CameraDriver", "name": f"cam{i}",
                        "parameters": {"width": self.width, "height": self.height, "fps": float(self.fps),
                                       "encoding": "rgb8", "frame_id": f"cam{i}", "content": self.content},
                        "extra_arguments": dict(ipc)})
        if self.lidar_points:
            out.append({"package": "components", "plugin": "components::LidarDriver", "name": "lidar",
                        "parameters": {"points_per_scan": self.lidar_points, "rate": float(self.lidar_rate)},
                        "extra_arguments": dict(ipc)})
        for i in range(self.imus):
            out.append({"package": "components", "plugin": "components::ImuDriver", "name": f"imu{i}",
                        "parameters": {"rate": float(self.imu_rate), "frame_id": f"imu{i}"},
                        "extra_arguments": dict(ipc)})
        return out

    def topics(self) -> dict[str, TopicSpec]:
        specs: list[TopicSpec] = []
        for i in range(self.cameras):
            specs.append(TopicSpec(f"/cam{i}/image_raw", "sensor_msgs/msg/Image", "image", self.fps))
            specs.append(TopicSpec(f"/cam{i}/camera_info", "sensor_msgs/msg/CameraInfo", "camera_info", self.fps,
                                   image_topic=f"/cam{i}/image_raw"))
        if self.lidar_points:
            specs.append(TopicSpec("/lidar/points", "sensor_msgs/msg/PointCloud2", "cloud", self.lidar_rate))
        for i in range(self.imus):
            specs.append(TopicSpec(f"/imu{i}/imu", "sensor_msgs/msg/Imu", "imu", self.imu_rate))
        for spec in specs:
            spec.size = serialized_size(self, spec)
        return {spec.name: spec for spec in specs}


_SIZE_CACHE: dict[tuple, int] = {}


def serialized_size(scenario: Scenario, spec: TopicSpec) -> int:
    """CDR size of one message of the topic, by serializing a sample like the driver's."""
    frame_id = spec.name.split("/")[1]
    key = (spec.kind, frame_id, scenario.width, scenario.height, scenario.lidar_points)
    if key not in _SIZE_CACHE:
        from rclpy.serialization import serialize_message
        _SIZE_CACHE[key] = len(serialize_message(sample_message(scenario, spec.kind, frame_id)))
    return _SIZE_CACHE[key]


def sample_message(scenario: Scenario, kind: str, frame_id: str) -> Any:
    """A message of ``kind`` shaped like the driver's (sizes only; the contents are zeros)."""
    from sensor_msgs.msg import CameraInfo, Image, Imu, PointCloud2, PointField
    from std_msgs.msg import Header
    header = Header(frame_id=frame_id)
    if kind == "image":
        msg: Any = Image(header=header, height=scenario.height, width=scenario.width, encoding="rgb8",
                         step=scenario.width * 3)
        msg.data = bytes(scenario.width * scenario.height * 3)
        return msg
    if kind == "camera_info":
        return CameraInfo(header=header, height=scenario.height, width=scenario.width,
                          distortion_model="plumb_bob", d=[0.0] * 5)
    if kind == "cloud":
        msg = PointCloud2(header=header, height=1, width=scenario.lidar_points, point_step=24,
                          row_step=24 * scenario.lidar_points, is_dense=True,
                          fields=[PointField(name=n, offset=o, datatype=7 if n != "ring" else 4, count=1)
                                  for n, o in (("x", 0), ("y", 4), ("z", 8), ("intensity", 12),
                                               ("ring", 16), ("time", 20))])
        msg.data = bytes(24 * scenario.lidar_points)
        return msg
    return Imu(header=header)


def s1_scenario(args: argparse.Namespace) -> Scenario:
    return Scenario("S1", "S1 multi-camera rig", args.seconds, cameras=args.cameras, width=args.width,
                    height=args.height, fps=args.fps, lidar_points=args.lidar_points, lidar_rate=args.lidar_rate,
                    imus=1, imu_rate=args.imu_rate)


def s2_scenario(args: argparse.Namespace, cameras: int) -> Scenario:
    rig = args.s2_base == "rig"
    return Scenario("S2", f"S2 ramp, {cameras} camera(s)", args.s2_seconds, cameras=cameras, width=args.width,
                    height=args.height, fps=args.fps, lidar_points=args.lidar_points if rig else 0,
                    lidar_rate=args.lidar_rate, imus=1 if rig else 0, imu_rate=args.imu_rate)


def s3_scenario(args: argparse.Namespace) -> Scenario:
    return Scenario("S3", "S3 IMU storm", args.s3_seconds, imus=args.s3_imus, imu_rate=args.s3_rate)
