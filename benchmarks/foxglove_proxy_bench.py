#!/usr/bin/env python3
"""What the bridge's subprotocol proxy costs: camera frames through it against straight to the SDK's server.

One process, no ROS: the Foxglove SDK's server on a loopback port, ``SubprotocolProxy`` in front of it (as
``components::FoxgloveBridge`` runs them), one channel of 1920x1080 rgb8 ``sensor_msgs/msg/Image`` frames (6.2 MB
of CDR each) logged by a feeder thread, and Foxglove's own client (tests/foxglove_client, node) subscribed to it,
decoding every frame. Modes, each its own window, alternated ``--repeat`` times:

* ``direct``: the client offers ``foxglove.sdk.v1`` to the SDK's port;
* ``proxy``: the client offers only ``foxglove.websocket.v1`` (as ``@foxglove/ws-protocol`` ships) to the proxy.

Rates: ``s1`` feeds 60 frames a second (the S1 rig's two 1080p30 cameras); ``max`` feeds as fast as the SDK takes
them (its outbox drops the oldest for a client that cannot keep up), so the client's rate is the path's limit.

Measured per window: frames the client decoded per second and their MB/s, the CPU seconds per GB of this
process (feeder, SDK, proxy) and of the proxy's threads alone, and the client's CPU seconds per second.

    python benchmarks/foxglove_proxy_bench.py [--seconds 10] [--repeat 2] [--quick]

Results: benchmarks/results/<date>-<commit>/foxglove_proxy.json.
"""
from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import foxglove  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from baglib.format.cdr_fast import serialize  # noqa: E402
from baglib.format.message_definitions import message_definition  # noqa: E402
from benchmarks.fleet_bench import TICK, cpu_seconds  # noqa: E402
from benchmarks.result_folder import add_run_arguments, run_header, save  # noqa: E402
from components.foxglove_bridge.subprotocol_proxy import SDK_SUBPROTOCOL, SubprotocolProxy  # noqa: E402
from ipc_testing.foxglove_client import FoxgloveClient, install_client  # noqa: E402

TOPIC = "/front_camera/image_raw"
PROXY_NAME = "foxglove:bench"
RATES = {"s1": 60.0, "max": 0.0}


def frame_cdr() -> bytes:
    image = Image(height=1080, width=1920, encoding="rgb8", step=1920 * 3)
    image.data = bytes(1920 * 1080 * 3)
    return bytes(serialize(image))


def thread_cpu_seconds(prefix: str) -> float:
    """CPU seconds of this process's live threads whose name starts with ``prefix``."""
    total = 0.0
    for thread in threading.enumerate():
        if thread.name.startswith(prefix) and thread.native_id is not None:
            with_stat = Path(f"/proc/self/task/{thread.native_id}/stat")
            try:
                fields = with_stat.read_text().rsplit(")", 1)[1].split()
            except FileNotFoundError:
                continue
            total += (int(fields[11]) + int(fields[12])) / TICK
    return total


class Feeder:
    """Logs the frame on the channel at ``fps`` (0: back to back), its sequence number in the first 8 bytes of
    the image data."""

    def __init__(self, channel: Any, fps: float) -> None:
        self._channel, self._fps = channel, fps
        self._frame = bytearray(frame_cdr())
        self._data_offset = len(self._frame) - 1920 * 1080 * 3
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="feeder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        sequence, next_at = 0, time.monotonic()
        while not self._stop.is_set():
            self._frame[self._data_offset:self._data_offset + 8] = sequence.to_bytes(8, "little")
            self._channel.log(bytes(self._frame), log_time=time.time_ns())
            sequence += 1
            if self._fps:
                next_at += 1.0 / self._fps
                self._stop.wait(max(0.0, next_at - time.monotonic()))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def run_window(mode: str, rate: str, seconds: float) -> dict[str, Any]:
    context = foxglove.Context()
    definition = message_definition("sensor_msgs/msg/Image")
    schema = foxglove.Schema(name="sensor_msgs/msg/Image", encoding=definition[0], data=definition[1].encode())
    channel = foxglove.Channel(TOPIC, schema=schema, message_encoding="cdr", context=context)
    server = foxglove.start_server(name="bench", host="127.0.0.1", port=0, context=context, message_backlog_size=32)
    proxy = SubprotocolProxy("127.0.0.1", 0, server.port, name=PROXY_NAME)
    feeder = Feeder(channel, RATES[rate])
    try:
        url, offered = ((f"ws://127.0.0.1:{server.port}", [SDK_SUBPROTOCOL]) if mode == "direct"
                        else (f"ws://127.0.0.1:{proxy.port}", []))
        with FoxgloveClient(url, offered) as client:
            client.subscribe(TOPIC)
            client.wait_messages(TOPIC, 10, timeout=60.0)  # connected, subscribed, warmed up
            before = (time.monotonic(), len(client.sequences(TOPIC)), cpu_seconds(os.getpid()),
                      thread_cpu_seconds(PROXY_NAME), cpu_seconds(client.process.pid))
            time.sleep(seconds)
            after = (time.monotonic(), len(client.sequences(TOPIC)), cpu_seconds(os.getpid()),
                     thread_cpu_seconds(PROXY_NAME), cpu_seconds(client.process.pid))
            sizes = {e["size"] for e in client.of("message")}
    finally:
        feeder.stop()
        server.stop()
        proxy.stop()
    elapsed, frames = after[0] - before[0], after[1] - before[1]
    gigabytes = frames * max(sizes) / 1e9
    return {"mode": mode, "rate": rate, "seconds": elapsed, "frames": frames, "fps": frames / elapsed,
            "mb_per_s": gigabytes * 1e3 / elapsed,
            "process_cpu_s_per_gb": (after[2] - before[2]) / gigabytes if gigabytes else None,
            "proxy_cpu_s_per_gb": (after[3] - before[3]) / gigabytes if gigabytes else None,
            "client_cpu_per_s": (after[4] - before[4]) / elapsed}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="window of every mode")
    parser.add_argument("--repeat", type=int, default=2, help="windows of each mode and rate, alternated")
    add_run_arguments(parser, quick="3 s windows, once")
    args = parser.parse_args()
    if args.quick:
        args.seconds, args.repeat = 3.0, 1
    install_client()
    report: dict[str, Any] = {**run_header("foxglove_proxy_bench.py", sys.argv[1:]), "seconds": args.seconds,
                              "load_before": os.getloadavg()[0], "windows": []}
    started = time.monotonic()
    for _ in range(args.repeat):
        for rate in RATES:
            for mode in ("direct", "proxy"):
                window = run_window(mode, rate, args.seconds)
                print({key: round(value, 3) if isinstance(value, float) else value for key, value in window.items()},
                      flush=True)
                report["windows"].append(window)
    report["elapsed_s"] = time.monotonic() - started
    report["load_after"] = os.getloadavg()[0]
    if args.results:
        print(f"results: {save(report, 'foxglove_proxy', Path(args.results))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
