"""``ipc-component top [CONTAINER]``: a live view of the containers in the domain, from their own reports.

Containers are found on the graph and listed through ListNodes (ipc_component.container_discovery); everything else
comes from the ``/diagnostics`` report each container publishes once a second (ipc_component.top_view): the
components, their status and drops, the topics each publishes with rate and bandwidth, free disk. Nothing is
loaded, called or changed but ListNodes.

On a terminal the view is redrawn once a second until ``q`` or Ctrl-C; with ``--once``, or when the output is not
a terminal, one plain-text snapshot is printed as soon as every container has sent two reports (rates need two),
about two seconds.
"""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from typing import Any

from ipc_component.ros_session import BUDGET, CliError, RosSession
from ipc_component.top_view import ContainerView, parse_reports, render

REFRESH = 1.0          # s between two frames of the live view
# s watching the graph for containers when none is named: longer than `list`'s, as the first rates take two
# reports (1 to 2 s) anyway; like `record status`.
DISCOVERY = 1.5
KEY_POLL = 0.1         # s: longest wait for the keyboard while spinning
REPORTS_BUDGET = 4.0   # s after listing for --once to get two reports of every container (they come every 1 s)
RELIST_BUDGET = 1.0    # s for re-listing the containers in the live view (when they changed)


class TopModel:
    """The containers shown: their listings, and their last two reports from a /diagnostics subscription."""

    def __init__(self, node: Any, only: str | None) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        from component_container.diagnostics import DIAGNOSTICS_TOPIC

        self.only = only
        self.views: dict[str, ContainerView] = {}
        self.listed: list[str] = []
        node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, self._on_array, 10)

    def _on_array(self, array: Any) -> None:
        for name, report in parse_reports(array.status).items():
            if self.only in (None, name):
                self.views.setdefault(name, ContainerView(name)).add(report)

    def set_listings(self, listings: Sequence[Any]) -> None:
        """The containers ListNodes found (container_discovery.ContainerListing): the ones shown from now on."""
        self.listed = [listing.container for listing in listings]
        for listing in listings:
            view = self.views.setdefault(listing.container, ContainerView(listing.container))
            view.listed, view.error = listing.components, listing.error
        for name in set(self.views) - set(self.listed):
            del self.views[name]

    def shown(self) -> list[ContainerView]:
        return [self.views[name] for name in self.listed]

    def reported_twice(self) -> bool:
        return all(view.previous is not None for view in self.shown())


def _list(ros: RosSession, model: TopModel, deadline: float, discovery_until: float) -> None:
    from ipc_component.container_discovery import list_containers

    model.set_listings(list_containers(ros.node, ros.executor, deadline=deadline, discovery_until=discovery_until,
                                       container=model.only))


def _relist_if_changed(ros: RosSession, model: TopModel) -> None:
    """List again when containers came or went, or a report names other components than the listing."""
    from ipc_component.container_discovery import find_containers

    found = [name for name in find_containers(ros.node) if model.only in (None, name)]
    if found != sorted(model.listed) or any(view.listing_is_stale() for view in model.shown()):
        now = time.monotonic()
        _list(ros, model, now + RELIST_BUDGET, now)


def _title(model: TopModel) -> list[str]:
    count = len(model.listed)
    return [f"ipc-component top  {time.strftime('%H:%M:%S')}  {count} container{'s' * (count != 1)}  "
            "(q: quit)", ""]


def _live(ros: RosSession, model: TopModel) -> None:
    from ipc_component.live_screen import LiveScreen

    with LiveScreen() as screen:
        next_frame = time.monotonic()
        try:
            while not screen.quit_pressed():
                if time.monotonic() >= next_frame:
                    _relist_if_changed(ros, model)
                    screen.draw(_title(model) + render(model.shown()))
                    next_frame = max(next_frame + REFRESH, time.monotonic())
                ros.executor.spin_once(timeout_sec=min(KEY_POLL, max(0.0, next_frame - time.monotonic())))
        except KeyboardInterrupt:
            return


def run_top(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    if args.spin_time < 0:
        raise CliError(f"Invalid --spin-time {args.spin_time:g}: must not be negative")
    start = time.monotonic()
    with RosSession(ros_args) as ros:
        model = TopModel(ros.node, args.container_node_name)  # subscribed first: reports come in while listing
        _list(ros, model, start + BUDGET, time.monotonic() + args.spin_time)
        if not model.listed:
            raise CliError((f"Unable to find container node '{args.container_node_name}'"
                            if args.container_node_name else "No container found") + f"\n    {ros.where_searched()}")
        if not args.once and sys.stdout.isatty():
            _live(ros, model)
            return 0
        deadline = time.monotonic() + REPORTS_BUDGET
        while not model.reported_twice() and time.monotonic() < deadline:
            ros.executor.spin_once(timeout_sec=min(KEY_POLL, max(0.0, deadline - time.monotonic())))
        print("\n".join(render(model.shown())), flush=True)
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("container_node_name", nargs="?", default=None,
                        help="only this container (default: every container in the domain)")
    parser.add_argument("--once", action="store_true",
                        help="print one plain-text snapshot and exit (what happens anyway when the output is not "
                             "a terminal)")
    parser.add_argument("--spin-time", type=float, default=DISCOVERY,
                        help=f"seconds to watch the graph for containers when none is named (default {DISCOVERY:g})")
    parser.set_defaults(handler=run_top)
