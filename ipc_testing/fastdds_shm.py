"""Which live processes Fast DDS has cut off from their shared-memory ports, read from ``/dev/shm`` and ``/proc``.

A participant reads its unicast traffic from shared-memory ports (``/dev/shm/fastrtps_port<N>`` on Fast DDS 2,
``fastdds_port<N>`` on Fast DDS 3), each held by its one reader through an exclusive lock on ``<port>_el``. Fast
DDS removes a port's segment when a process finds the port broken (its mutex held by a writer that was killed
holding it, a health check that timed out) and creates a new one under the same name. The reader, still holding
the lock, goes on reading the old segment, which no longer has a name. Peers that had the port open still write into
the old segment; every participant that starts afterwards opens the port by its name and writes into the new one,
which nobody reads: no newcomer reaches the process, for good, and the next participant that tries the port logs
``Failed init_port ...: open_and_lock_file failed``. A test that waits in vain for such a process sees only silence;
:func:`describe_stranded` says what happened.
"""
from __future__ import annotations

import re
from pathlib import Path

SHM = Path("/dev/shm")
#: A port's segment: Fast DDS 2's and 3's names.
PORT = re.compile(r"(fastrtps|fastdds)_port\d+")


def _locked_inodes() -> dict[int, int]:
    """The inode of every file an flock() holds exclusively, and the holder's process id (``/proc/locks``)."""
    held = {}
    for line in Path("/proc/locks").read_text().splitlines():
        fields = line.split()
        if len(fields) >= 6 and fields[1] == "FLOCK" and fields[3] == "WRITE":
            held[int(fields[5].rsplit(":", 1)[1])] = int(fields[4])
    return held


def _inode(path: Path) -> int | None:
    try:
        return path.stat().st_ino
    except FileNotFoundError:
        return None


def read_ports() -> dict[int, list[str]]:
    """Per live process id, the shared-memory ports it reads (holds the ``_el`` lock of), by segment name."""
    holders = _locked_inodes()
    ports: dict[int, list[str]] = {}
    for lock in sorted(SHM.glob("*_el")):
        name = lock.name.removesuffix("_el")
        pid = holders.get(_inode(lock) or -1)
        if pid is not None and PORT.fullmatch(name):
            ports.setdefault(pid, []).append(name)
    return ports


def _mapped(pid: int) -> dict[str, int]:
    """The shared-memory segments ``pid`` maps: name (with " (deleted)" once unlinked) to inode."""
    mapped = {}
    try:
        lines = Path(f"/proc/{pid}/maps").read_text().splitlines()
    except (FileNotFoundError, ProcessLookupError):
        return mapped
    for line in lines:
        fields = line.split(maxsplit=5)
        if len(fields) == 6 and fields[5].startswith(f"{SHM}/"):
            mapped[fields[5][len(str(SHM)) + 1:]] = int(fields[4])
    return mapped


def stranded() -> dict[int, list[str]]:
    """Per live process, the ports it reads whose segment is no longer the one it maps (gone or made anew)."""
    cut = {}
    for pid, names in read_ports().items():
        mapped = _mapped(pid)
        lost = [name for name in names
                if f"{name} (deleted)" in mapped or (name in mapped and _inode(SHM / name) != mapped[name])]
        if lost:
            cut[pid] = lost
    return cut


def describe_stranded() -> str:
    """A sentence naming every process Fast DDS cut off from its shared-memory ports, with its command line;
    '' if none is."""
    cut = stranded()
    if not cut:
        return ""
    named = []
    for pid, ports in sorted(cut.items()):
        try:
            command = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except FileNotFoundError:
            continue
        named.append(f"process {pid} ({command.strip()[:120]}) reads {', '.join(ports)}")
    return ("Fast DDS removed the shared-memory ports of live processes, which no participant started since reaches: "
            + "; ".join(named)) if named else ""
