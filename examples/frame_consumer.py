"""A Python consumer that runs inside the container: ``frame_consumer:FrameConsumer``.

Loaded next to a player (or the drivers) with ``use_intra_process_comms``, it receives each camera frame and
point cloud as the object the publisher made, by reference: a 1080p frame costs it no copy and no
deserialization. It logs what it sees once a second and a summary when it is unloaded; a real pipeline would
run its detector where ``_on_image`` counts bytes.

Load it with a container started with ``--allow-module-plugins`` from this directory:
``ipc-component load /ComponentManager frame_consumer frame_consumer:FrameConsumer -e use_intra_process_comms:=true``
"""
from __future__ import annotations

import time
from collections import Counter
from typing import Any

from sensor_msgs.msg import Image, PointCloud2

from component_container import ComponentNode


class FrameConsumer(ComponentNode):
    """Counts frames and clouds per topic (parameters ``image_topics``, ``cloud_topics``)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("frame_consumer", **kwargs)
        image_topics = self.declare_parameter(
            "image_topics", ["/front_camera/image_raw", "/rear_camera/image_raw"]).value
        cloud_topics = self.declare_parameter("cloud_topics", ["/lidar/points"]).value
        self.counts: Counter[str] = Counter()
        self.payload_bytes = 0
        self._window: Counter[str] = Counter()
        self._started = time.monotonic()
        self._inputs = [self.create_subscription(Image, t, self._on_image, 10) for t in image_topics]
        self._inputs += [self.create_subscription(PointCloud2, t, self._on_cloud, 10) for t in cloud_topics]
        self._timer = self.create_timer(1.0, self._log_rates)

    def _on_image(self, msg: Image) -> None:
        self._count(msg.header.frame_id or "image", len(msg.data))

    def _on_cloud(self, msg: PointCloud2) -> None:
        self._count(msg.header.frame_id or "cloud", len(msg.data))

    def _count(self, source: str, size: int) -> None:
        self.counts[source] += 1
        self._window[source] += 1
        self.payload_bytes += size

    def _log_rates(self) -> None:
        if self._window:
            rates = ", ".join(f"{source} {count}/s" for source, count in sorted(self._window.items()))
            self.get_logger().info(f"in-process: {rates}")
            self._window.clear()

    def destroy_node(self) -> None:
        seconds = time.monotonic() - self._started
        self.get_logger().info(
            f"consumed {sum(self.counts.values())} messages ({self.payload_bytes / 1e9:.2f} GB of payload) in "
            f"{seconds:.1f} s: " + ", ".join(f"{source} {count}" for source, count in sorted(self.counts.items())))
        super().destroy_node()
