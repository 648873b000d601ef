"""``ipc-component record status``: one table of every recorder in the domain, once or live (``--watch``).

Recorders are found by what they are (ipc_component.recorder_lookup: the services every ``components::Recorder``
offers, placed in their container through ListNodes), so recorders loaded by hand are listed too; the figures come from ``~/get_stats``
(what the recorder already reports live: bytes, messages, drops, free space, the time until the disk's
reserve is reached) and the host from the container's clock service. Nothing is loaded or changed.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Sequence

from baglib.format import fleet_keys
from baglib.upload.journal import summary_text
from ipc_component.recorder_lookup import find_recorders
from ipc_component.ros_session import BUDGET, RosSession
from ipc_component.text_table import format_table
from ipc_component.verb_arguments import add_verb

if TYPE_CHECKING:
    from ipc_component.fleet_link import ContainerLink

HEADER = ("HOST", "CONTAINER", "SESSION", "BAG", "ELAPSED", "MB/S", "MESSAGES", "DROPS", "FREE", "TO FULL", "UPLOAD")


@dataclass
class Sample:
    """One recorder's stats at one moment (monotonic seconds)."""

    when: float
    stats: dict[str, Any]


def _row(link: ContainerLink, node_name: str, sample: Sample, previous: Sample | None) -> tuple[str, ...]:
    stats = sample.stats
    current = stats.get("current") or {}
    custom = stats.get("custom_data") or {}
    start_ns, end_ns = stats.get("window_ns") or (0, 0)
    now_ns = time.time_ns()
    if not stats["recording"]:
        elapsed = "finished" if stats.get("finished") else "stopped"
    elif now_ns < start_ns:
        elapsed = f"in {(start_ns - now_ns) / 1e9:.1f} s"
    else:
        elapsed = f"{(min(now_ns, end_ns or now_ns) - start_ns) / 1e9:.1f} s"
    written = current.get("bytes_written", 0)
    if previous is not None and previous.stats.get("current") and sample.when > previous.when:
        rate = (written - previous.stats["current"]["bytes_written"]) / (sample.when - previous.when)
    else:
        rate = written / max((now_ns - start_ns) / 1e9, 1e-3) if stats["recording"] and now_ns > start_ns else 0.0
    topics = (current.get("topics") or {}).values()
    left = current.get("seconds_until_min_free")
    return (link.host, link.name, custom.get(fleet_keys.SESSION, "-"), current.get("bag", node_name), elapsed,
            f"{rate / 1e6:.1f}", str(sum(t["written"] for t in topics)), str(sum(t["dropped"] for t in topics)),
            f"{current['free_bytes'] / 1e9:.1f} GB" if "free_bytes" in current else "-",
            "-" if left is None else f"{left / 60:.0f} min", summary_text(stats.get("upload")))


def run_status(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    from std_srvs.srv import Trigger

    with RosSession(ros_args) as ros:
        placed = [(recorder.container, recorder.node)
                  for recorder in find_recorders(ros, args.spin_time, args.session, fleet_only=False)]
        fleet = ros.fleet(sorted({container for container, _ in placed}))
        fleet.connect(time.monotonic() + BUDGET)
        links = {link.name: link for link in fleet.links}
        clients = {(c, n): fleet.component_client(links[c], Trigger, f"{n}/get_stats") for c, n in placed}
        previous: dict[tuple[str, str], Sample] = {}
        for round_number in range(args.count if args.watch else 1):
            replies = fleet.repeat_all({f"{c}\n{n}": (client, Trigger.Request()) for (c, n), client in clients.items()},
                                       time.monotonic() + BUDGET)
            rows = []
            for (c, n) in placed:
                reply = replies.get(f"{c}\n{n}")
                if reply is None:
                    rows.append((links[c].host or "?", c, "-", n, "no reply", "-", "-", "-", "-", "-", "-"))
                    continue
                sample = Sample(time.monotonic(), json.loads(reply.message))
                rows.append(_row(links[c], n, sample, previous.get((c, n))))
                previous[(c, n)] = sample
            if args.watch:
                print("\033[H\033[J" if round_number else "", end="")
            print("\n".join(format_table(HEADER, rows)), flush=True)
            if args.watch and round_number + 1 < args.count:
                fleet.spin_until(lambda: False, time.monotonic() + args.interval)
    return 0


def add_arguments(record_verbs: Any) -> None:
    p = add_verb(record_verbs, "status", "One table of every recorder in the domain")
    p.add_argument("--session", help="only this fleet session's recorders")
    p.add_argument("--watch", action="store_true", help="refresh the table until interrupted (Ctrl-C)")
    p.add_argument("--interval", type=float, default=1.0, help="seconds between refreshes with --watch")
    p.add_argument("--count", type=int, default=2**31, help=argparse.SUPPRESS)
    p.add_argument("--spin-time", type=float, default=1.5, help="seconds to discover containers")
    p.set_defaults(handler=run_status)
