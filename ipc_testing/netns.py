"""Several computers on one machine: Linux network namespaces joined by a bridge that reaches nothing outside.

Each host is a network namespace with one veth link to a private bridge (no uplink, no address in the root
namespace) and, for the processes started in it, a UTS namespace with its own host name. An extra namespace,
the operator's, is where fleet commands run, as from a laptop on the robot's network. DDS discovery inside the
namespaces uses multicast on that bridge (``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET``: the subnet is the bridge)
and only UDP (``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``): Fast DDS would otherwise pass data between processes of
one machine through shared memory, which no network partition cuts.

Taking a host's link down (:meth:`Network.cut`) partitions it from the others. Needs root (CAP_NET_ADMIN and
CAP_SYS_ADMIN); :func:`unavailable` says why not where that is missing.

A network outlives a test process that is killed (SIGKILL, or a run stopped mid-test): namespaces and bridges are
the kernel's, not the process's. Each network therefore records its owner (pid and start time) under
:data:`OWNERS` before it makes anything, and every new network first removes those whose owner is gone
(:func:`remove_stale`).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

#: The private subnet of the bridge: 10.213.<n>.0/24 with n chosen per network so that parallel runs differ.
SUBNET = "10.213"
OPERATOR = "operator"
#: One file per network (named by its tag) holding its owner's pid and start time; tmpfs, as /run/netns is.
OWNERS = Path("/run/ipc_testing_netns")


def unavailable() -> str | None:
    """Why network namespaces cannot be made here, or None when they can."""
    if os.geteuid() != 0:
        return "network namespaces need root (CAP_NET_ADMIN, CAP_SYS_ADMIN)"
    for tool in ("ip", "unshare"):
        if shutil.which(tool) is None:
            return f"the '{tool}' command is missing"
    probe = subprocess.run(["unshare", "--net", "--uts", "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        return f"cannot create namespaces: {probe.stderr.strip()}"
    return None


def _start_time(pid: int) -> str | None:
    """The start time of process ``pid`` (clock ticks after boot), or None if there is no such process: with the
    pid, it names one process, whatever pid reuse came since."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat[stat.rindex(")") + 2:].split()[19]


def remove_stale() -> list[str]:
    """Remove the namespaces and bridge of every recorded network whose owner process is gone; their tags."""
    removed = []
    for record in sorted(OWNERS.glob("*")):
        try:
            pid, _, started = record.read_text().partition(" ")
        except FileNotFoundError:  # its owner removed it meanwhile
            continue
        if not pid.isdigit() or _start_time(int(pid)) == started.strip():
            continue  # a record being written (see Network.__enter__) or a live owner's
        tag = record.name
        listing = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
        for namespace in (line.split()[0] for line in listing.splitlines() if line.startswith(f"ipc{tag}")):
            subprocess.run(["ip", "netns", "del", namespace], capture_output=True)  # takes its veth pair along
        subprocess.run(["ip", "link", "del", f"ipcbr{tag}"], capture_output=True)
        record.unlink(missing_ok=True)
        removed.append(tag)
    return removed


def _ip(*args: str, namespace: str | None = None) -> None:
    command = ["ip", *args] if namespace is None else ["ip", "netns", "exec", namespace, "ip", *args]
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        raise OSError(f"{' '.join(command)}: {result.stderr.strip()}")


@dataclass
class Host:
    name: str
    namespace: str
    address: str
    link: str  # the bridge end of its veth pair, in the root namespace


class Network:
    """``hosts`` computers plus the operator's, on one private bridge; a context manager that removes it all."""

    def __init__(self, hosts: Sequence[str]) -> None:
        tag = uuid.uuid4().hex[:6]
        self.tag = tag
        self.bridge = f"ipcbr{tag}"
        subnet = f"{SUBNET}.{int(tag, 16) % 250 + 1}"
        self.hosts = {name: Host(name, f"ipc{tag}{name}", f"{subnet}.{i + 10}", f"ipc{tag}{i}")
                      for i, name in enumerate([*hosts, OPERATOR])}
        self._made: list[Host] = []

    def __enter__(self) -> "Network":
        remove_stale()
        OWNERS.mkdir(parents=True, exist_ok=True)
        written = OWNERS.parent / f".ipc_testing_netns.{self.tag}"  # outside OWNERS: never read half-written
        written.write_text(f"{os.getpid()} {_start_time(os.getpid())}")
        os.replace(written, OWNERS / self.tag)
        try:
            _ip("link", "add", self.bridge, "type", "bridge")
            _ip("link", "set", self.bridge, "up")
            for host in self.hosts.values():
                self._add(host)
        except BaseException:
            self.__exit__()
            raise
        return self

    def _add(self, host: Host) -> None:
        _ip("netns", "add", host.namespace)
        self._made.append(host)
        _ip("link", "add", host.link, "type", "veth", "peer", "name", "eth0", "netns", host.namespace)
        _ip("link", "set", host.link, "master", self.bridge)
        _ip("link", "set", host.link, "up")
        _ip("addr", "add", f"{host.address}/24", "dev", "eth0", namespace=host.namespace)
        _ip("link", "set", "eth0", "up", namespace=host.namespace)
        _ip("link", "set", "lo", "up", namespace=host.namespace)
        _ip("route", "add", "224.0.0.0/4", "dev", "eth0", namespace=host.namespace)  # DDS discovery multicast

    def __exit__(self, *exc: object) -> None:
        for host in self._made:
            subprocess.run(["ip", "link", "del", host.link], capture_output=True)
            subprocess.run(["ip", "netns", "del", host.namespace], capture_output=True)
        self._made.clear()
        subprocess.run(["ip", "link", "del", self.bridge], capture_output=True)
        (OWNERS / self.tag).unlink(missing_ok=True)

    def prefix(self, host: str) -> list[str]:
        """A command prefix that runs the rest in ``host``'s namespaces, with its host name; it execs, so the pid
        of the process started is the pid of the command that follows."""
        return ["ip", "netns", "exec", self.hosts[host].namespace, "unshare", "--uts", "--",
                "sh", "-c", 'hostname "$0" && exec "$@"', host]

    @staticmethod
    def environment(domain_id: int) -> Mapping[str, str]:
        """ROS settings for processes in the namespaces (the bridge is the subnet; UDP only)."""
        return {"ROS_DOMAIN_ID": str(domain_id), "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
                "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4", "ROS_STATIC_PEERS": ""}

    def cut(self, host: str) -> None:
        """Partition ``host`` from everyone else (its link to the bridge goes down)."""
        _ip("link", "set", self.hosts[host].link, "down")

    def mend(self, host: str) -> None:
        _ip("link", "set", self.hosts[host].link, "up")
