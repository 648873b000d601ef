"""A real MCAP bag of camera frames and IMU messages, written with this project's BagWriter, for what needs bags
without running a rig: the upload benchmark's files and the bags the cluster test reads back from the store.

The messages are ROS messages serialized by rclpy (real CDR): ``sensor_msgs/msg/Image`` rgb8 frames whose pixels
are random (incompressible, as the camera driver's default content) with the frame's sequence number in their
first 8 bytes (as the driver's), and ``sensor_msgs/msg/Imu`` at ``imu_rate``. A few random frames are reused with
new sequence numbers, so a bag of gigabytes costs no more random bytes than a few frames.
"""
from __future__ import annotations

import os
from pathlib import Path

#: The first message's time (ns): 2023-11-14.
T0 = 1_700_000_000_000_000_000
#: Distinct random frames per camera, reused in turn.
RANDOM_FRAMES = 4


def camera_topic(camera: int) -> str:
    return f"/cam{camera}/image_raw"


IMU_TOPIC = "/imu/imu"


def write_camera_bag(path: Path, frames: int, cameras: int = 2, width: int = 1920, height: int = 1080,
                     fps: float = 30.0, imu_rate: float = 200.0, max_bagfile_size: int = 0,
                     start_ns: int = T0) -> dict[str, int]:
    """Write ``frames`` frames per camera (and the IMU messages of the same span) into a new MCAP bag at ``path``,
    split every ``max_bagfile_size`` bytes (0: one file); the messages written per topic."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Image, Imu
    from std_msgs.msg import Header

    from baglib.format.metadata import TopicInfo
    from baglib.write.writer import BagWriter

    def header(frame_id: str, stamp_ns: int) -> Header:
        msg = Header(frame_id=frame_id)
        msg.stamp.sec, msg.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        return msg

    pixels = [bytearray(os.urandom(width * height * 3)) for _ in range(RANDOM_FRAMES)]
    period_ns, imu_period_ns = round(1e9 / fps), round(1e9 / imu_rate) if imu_rate else 0
    counts = {camera_topic(camera): 0 for camera in range(cameras)}
    if imu_period_ns:
        counts[IMU_TOPIC] = 0
    with BagWriter(path, max_bagfile_size=max_bagfile_size) as writer:
        for topic in counts:
            writer.add_topic(TopicInfo(topic, "sensor_msgs/msg/Imu" if topic == IMU_TOPIC else "sensor_msgs/msg/Image"))
        next_imu_ns = start_ns
        for sequence in range(frames):
            stamp_ns = start_ns + sequence * period_ns
            while imu_period_ns and next_imu_ns <= stamp_ns:
                writer.write(IMU_TOPIC, serialize_message(Imu(header=header("imu", next_imu_ns))), next_imu_ns,
                             next_imu_ns)
                counts[IMU_TOPIC] += 1
                next_imu_ns += imu_period_ns
            for camera in range(cameras):
                data = pixels[(sequence + camera) % RANDOM_FRAMES]
                data[:8] = sequence.to_bytes(8, "little")
                image = Image(header=header(f"cam{camera}", stamp_ns), height=height, width=width, encoding="rgb8",
                              step=width * 3)
                image.data = bytes(data)
                writer.write(camera_topic(camera), serialize_message(image), stamp_ns, stamp_ns)
                counts[camera_topic(camera)] += 1
    return counts
