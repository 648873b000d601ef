"""Process-wide settings change only when the container is told to (``--low-latency``), never because a
component was loaded: a player used to shorten the interpreter's switch interval and retune malloc for every
other component of its container. And ``release_free_memory`` gives back what malloc keeps after a peak."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from test_bag_play import chatter_bag

#: Loads a Player on a real bag in an in-process manager (after applying the container's tuning when asked to)
#: and prints the switch interval before and after the load, and whether the tuning was applied. The player's
#: warning goes to stderr.
SCRIPT = """
import sys
import rclpy
from rclpy.context import Context
from component_container.component_manager import ComponentManager
from component_container.process_tuning import apply_low_latency, low_latency
from component_container.startup_file import load_request

low = sys.argv[2] == "low"
if low:
    apply_low_latency()
before = sys.getswitchinterval()
context = Context()
rclpy.init(context=context)
manager = ComponentManager("single", node_name="tuning_probe", context=context)
request = load_request({"package": "components", "plugin": "components::Player",
                        "parameters": {"storage.uri": sys.argv[1], "play.start_paused": True}}, 1, "test")
manager.load(request)
after = sys.getswitchinterval()
manager.shutdown()
manager.destroy_node()
rclpy.try_shutdown(context=context)
print(before, after, low_latency() is not None)
"""


def run(bag: Path, mode: str) -> tuple[float, float, bool, str]:
    result = subprocess.run([sys.executable, "-c", SCRIPT, str(bag), mode], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    before, after, applied = result.stdout.split()
    return float(before), float(after), applied == "True", result.stderr


def test_a_player_changes_no_process_setting(tmp_path: Path) -> None:
    default = sys.getswitchinterval()
    before, after, applied, log = run(chatter_bag(tmp_path / "bag", 3, 10), "default")
    assert (before, after, applied) == (default, default, False)
    assert "runs without --low-latency" in log  # the player says what it needs instead


def test_the_container_applies_low_latency_when_told(tmp_path: Path) -> None:
    before, after, applied, log = run(chatter_bag(tmp_path / "bag", 3, 10), "low")
    assert before == after <= 0.0002 < sys.getswitchinterval()
    assert applied
    assert "runs without --low-latency" not in log


#: Frees one 8 MB buffer (glibc then serves smaller big requests from the heap, as in a long-running container),
#: holds 40 frames of 6 MB allocated on another thread among small objects that stay, frees them, and prints the
#: resident size after the free and after release_free_memory, in MiB.
PEAK_SCRIPT = """
import threading
from component_container.process_tuning import release_free_memory, resident_bytes

buffer = bytearray(8_000_000)
del buffer
frames, small = [], []

def allocate():
    for n in range(40):
        frames.append(bytearray(6_220_800))
        small.append(bytearray(2000))

thread = threading.Thread(target=allocate)
thread.start()
thread.join()
held = resident_bytes()
frames.clear()
freed = resident_bytes()
assert release_free_memory()
print(held >> 20, freed >> 20, resident_bytes() >> 20)
"""


def test_release_free_memory_gives_a_freed_peak_back() -> None:
    result = subprocess.run([sys.executable, "-c", PEAK_SCRIPT], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    held, freed, released = (int(value) for value in result.stdout.split())
    assert freed > held - 40  # malloc kept the 240 MB it was given back
    assert released < freed - 200, (held, freed, released)

