"""The bridge's own thread: takes queued messages, serializes the in-process ones, hands them to the SDK.

In-process messages arrive as Python objects and are serialized here, never in the publisher's thread, and
only for channels a client is subscribed to (the bridge has no subscription otherwise). The serializer is the
recorder's (baglib.format.cdr_fast: images, point clouds and IMU messages without rclpy's copies; the rest
through rclpy); CDR bytes from DDS go out as they came. The SDK copies each message into the outbox of every
subscribed client, which drops that client's oldest message when it is full: a slow client never blocks this
thread, and this thread never blocks a publisher.

Channels are served round-robin, one message each per pass, so a burst of camera frames does not hold back
the IMU.
"""
from __future__ import annotations

import threading
from typing import Callable

from components.foxglove_bridge.channel_registry import BridgeChannel


class Forwarder:
    """Runs the forwarding loop on a thread of its own until :meth:`stop`."""

    def __init__(self, channels: Callable[[], list[BridgeChannel]], warn: Callable[[str], None],
                 name: str = "foxglove_bridge") -> None:
        self._channels = channels
        self._warn = warn
        self._wake = threading.Event()
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        """Called by every offer: cheap when the thread is already awake."""
        if not self._wake.is_set():
            self._wake.set()

    def _run(self) -> None:
        while not self._stopping:
            self._wake.wait()
            self._wake.clear()
            self._drain()

    def _drain(self) -> None:
        channels = self._channels()
        while not self._stopping:
            busy = False
            for channel in channels:
                busy = self._send_next(channel) or busy
            if not busy:
                return

    def _send_next(self, channel: BridgeChannel) -> bool:
        """Send the channel's oldest queued message, if any; whether there was one."""
        item = channel.queue.take()
        if item is None:
            return False
        message, log_time = item
        del item
        data = channel.serialize(message, self._warn)
        del message  # an in-process frame goes back to its publisher's ring as soon as it is serialized
        if data is not None:
            channel.send(data, log_time)
        return True

    def stop(self, timeout: float = 2.0) -> None:
        self._stopping = True
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout)
