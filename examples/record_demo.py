"""The main demo: record a simulated sensor rig with the zero-copy recorder, then replay it into a Python
consumer, the way a user would.

1. start a container with two 1080p cameras, a LiDAR and an IMU (examples/sensors.yaml);
2. load the recorder into it with ``ipc-component load`` (intra-process: frames arrive by reference);
3. record for a few seconds, then unload the recorder: the bag is finalized while the drivers keep running;
4. print ``ipc-component bag info`` and stop the container;
5. start a second container running ``frame_consumer:FrameConsumer`` (examples/frame_consumer.py), load a
   ``components::Player`` of the bag next to it (intra-process: each frame is deserialized once and handed
   to the consumer by reference), let it play to the end and unload both: the consumer logs what it got.

Usage: ``python examples/record_demo.py [--seconds 5] [--output DIR] [--storage mcap|sqlite3] [--no-replay]``
(without ``--output`` the bag goes to a temp dir that is deleted at the end).
The run stays on this machine: a random ROS_DOMAIN_ID unless one is set, discovery limited to localhost.
"""
from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parent
CONTAINER = "/ComponentManager"


def cli(*args: str) -> str:
    """Run ``ipc-component`` and return its output; exit with its message if it fails."""
    command = [str(Path(sys.executable).with_name("ipc-component")), *args]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    if result.returncode != 0:
        sys.exit(f"'ipc-component {' '.join(args)}' failed:\n{result.stdout}{result.stderr}")
    return result.stdout


def wait_for_container(components: int = 4, timeout: float = 30.0) -> None:
    """Until the container answers ListNodes with at least ``components`` components."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        result = subprocess.run([str(Path(sys.executable).with_name("ipc-component")), "list", CONTAINER],
                                capture_output=True, text=True, timeout=60)
        if result.returncode == 0 and len(result.stdout.splitlines()) >= components:
            return
        time.sleep(0.5)
    sys.exit(f"the container did not come up with {components} components within {timeout} s")


def stop(container: subprocess.Popen) -> None:
    """SIGINT (unload everything, finalize bags), then wait; kill only if it overruns."""
    container.send_signal(signal.SIGINT)
    try:
        container.wait(timeout=30)
    except subprocess.TimeoutExpired:
        container.kill()
        container.wait()


def record_rig(bag: Path, seconds: float, storage: str) -> None:
    """Record ``seconds`` of the rig into ``bag``: a container with the drivers, a recorder loaded next to them
    and unloaded again (the bag is finalized while the drivers keep running)."""
    print(f"Starting a container with the sensor rig (ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']})")
    container = subprocess.Popen([sys.executable, "-m", "component_container", "--executor", "multi",
                                  "--load", str(EXAMPLES / "sensors.yaml"), "--ros-args", "-p", "thread_num:=2"])
    try:
        wait_for_container()
        print(cli("list", CONTAINER))
        uid = cli("load", CONTAINER, "components", "components::Recorder", "-n", "recorder", "-q",
                  "-p", "record.all_topics:=true", "-p", "record.exclude_regex:=^/(rosout|parameter_events)$",
                  "-p", f"storage.uri:={bag}", "-p", f"storage.storage_id:={storage}",
                  "-e", "use_intra_process_comms:=true").split()[0]
        print(f"Recorder loaded as component {uid}; recording {seconds:g} s to {bag}")
        time.sleep(seconds)
        print(cli("unload", CONTAINER, uid), end="")
        print("Drivers still running after the recorder was unloaded:")
        print(cli("list", CONTAINER))
    finally:
        stop(container)


def replay_into_consumer(bag: Path, seconds: float) -> None:
    """Play ``bag`` into a container where a Python consumer takes the frames in-process."""
    print("Starting a container with an in-process consumer, then a player of the bag next to it")
    container = subprocess.Popen([sys.executable, "-m", "component_container", "--use-intra-process-comms", "--low-latency",
                                  "--allow-module-plugins"], cwd=EXAMPLES)
    try:
        wait_for_container(components=0)
        consumer = cli("load", CONTAINER, "frame_consumer", "frame_consumer:FrameConsumer", "-q").split()[0]
        player = cli("load", CONTAINER, "components", "components::Player", "-n", "player", "-q",
                     "-p", f"storage.uri:={bag.resolve()}").split()[0]
        time.sleep(seconds + 3.0)  # the bag's duration, plus reading ahead and the last messages
        print(cli("unload", CONTAINER, player, consumer), end="")
    finally:
        stop(container)


def isolate() -> None:
    """Keep every ROS run of the demo on this machine, in a domain of its own."""
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 100)))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="how long to record (default 5)")
    parser.add_argument("--output", default=None,
                        help="directory to keep the bag in (default: a temp dir, deleted at the end)")
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    parser.add_argument("--no-replay", action="store_true", help="skip step 5 (replay into a consumer)")
    args = parser.parse_args()
    isolate()
    output = Path(args.output or tempfile.mkdtemp(prefix="ipc_demo_"))
    bag = output / "demo_bag"

    try:
        record_rig(bag, args.seconds, args.storage)
        print(cli("bag", "info", str(bag)))
        if not args.no_replay:
            replay_into_consumer(bag, args.seconds)
    finally:
        if args.output is None:  # a few seconds of this rig are gigabytes: do not leave them in /tmp
            shutil.rmtree(output, ignore_errors=True)
            print(f"(deleted {output}; pass --output DIR to keep the bag)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
