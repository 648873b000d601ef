"""The network-namespace harness (ipc_testing.netns) cleans up after a test process that was killed mid-test."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from ipc_testing.netns import OWNERS, Network, remove_stale, unavailable
from ipc_testing.process import stop_process

pytestmark = pytest.mark.skipif(unavailable() is not None, reason=f"no network namespaces: {unavailable()}")

REPO = Path(__file__).resolve().parents[1]
OWNER = """
import time
from ipc_testing.netns import Network
network = Network(["k1", "k2"]).__enter__()
print(network.tag, flush=True)
time.sleep(600)
"""


def namespaces(tag: str) -> list[str]:
    listing = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=True).stdout
    return [line.split()[0] for line in listing.splitlines() if line.startswith(f"ipc{tag}")]


def link_exists(name: str) -> bool:
    return subprocess.run(["ip", "link", "show", name], capture_output=True).returncode == 0


def test_a_network_whose_owner_was_killed_is_removed_by_the_next_one() -> None:
    """A process killed (SIGKILL) while its network exists leaves its namespaces and bridge behind; the next
    network removes them first, and leaves a live owner's network alone."""
    owner = subprocess.Popen([sys.executable, "-c", OWNER], stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        tag = owner.stdout.readline().strip()
        assert tag and len(namespaces(tag)) == 3 and link_exists(f"ipcbr{tag}"), tag  # two hosts, the operator
        with Network(["n1"]) as alive:
            assert len(namespaces(tag)) == 3, "a network whose owner runs was removed"
            stop_process(owner, 9)
            with Network(["n2"]):
                assert namespaces(tag) == [] and not link_exists(f"ipcbr{tag}"), "the killed owner's network is left"
                assert not (OWNERS / tag).exists()
            assert len(namespaces(alive.tag)) == 2
    finally:
        if owner.poll() is None:
            stop_process(owner, 9)
        remove_stale()


def test_a_record_without_an_owner_yet_is_not_taken_for_a_dead_one() -> None:
    """Records appear whole (written aside, then renamed), so a record that names no pid is not a dead owner's:
    its network is left alone (a parallel worker's, being made)."""
    tag = "0badc0"
    OWNERS.mkdir(parents=True, exist_ok=True)
    (OWNERS / tag).write_text("")
    subprocess.run(["ip", "netns", "add", f"ipc{tag}h1"], check=True)
    try:
        remove_stale()
        assert namespaces(tag) == [f"ipc{tag}h1"], "a network whose record names no owner was removed"
    finally:
        subprocess.run(["ip", "netns", "del", f"ipc{tag}h1"], capture_output=True)
        (OWNERS / tag).unlink(missing_ok=True)
