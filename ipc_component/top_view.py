"""What ``ipc-component top`` shows: containers' ``/diagnostics`` reports read back, rates, and the text.

A container reports once a second (component_container.diagnostics): a status ``<container>: container`` with
its uptime and free disk, and a status ``<container>: <component>`` per component with its level and message,
its drops and free disk when it reports them (component_container.health), and what each of its topics has
published so far (component_container.publish_counts). Rates and bandwidth come from two reports: the messages
and bytes published between them, over the time between the last publish before each. Nothing here talks ROS.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from component_container.health import DROPPED, ERROR, FREE_DISK_MB, OK, WARN
from component_container.publish_counts import UPTIME, Published, parse_publication
from ipc_component.text_table import format_table

CONTAINER_STATUS = "container"
HEADER = ("ID", "COMPONENT", "TOPIC", "RATE (Hz)", "BANDWIDTH", "DROPS", "FREE DISK", "STATUS")
STALE = 3  # diagnostic_msgs/DiagnosticStatus.STALE, which aggregators use
LEVELS = {OK: "", WARN: "WARN ", ERROR: "ERROR ", STALE: "STALE "}


@dataclass
class Status:
    """One status of a report: level, message, values, and the topics the component published on."""

    level: int
    message: str
    values: dict[str, str]
    published: dict[str, Published] = field(default_factory=dict)

    @property
    def text(self) -> str:
        return LEVELS.get(self.level, f"level {self.level} ") + self.message


@dataclass
class Report:
    """One ``/diagnostics`` report of one container: its uptime (s) when taken, its status and its components'."""

    uptime: float
    container: Status
    components: dict[str, Status]


def parse_status(status: Any) -> Status:
    """A diagnostic_msgs/DiagnosticStatus (any object with its fields) as a :class:`Status`."""
    level = status.level[0] if isinstance(status.level, (bytes, bytearray)) else int(status.level)
    values, published = {}, {}
    for pair in status.values:
        topic = parse_publication(pair.key, pair.value)
        if topic is None:
            values[pair.key] = pair.value
        else:
            published[topic[0]] = topic[1]
    return Status(level, status.message, values, published)


def parse_reports(statuses: Iterable[Any]) -> dict[str, Report]:
    """The container reports among the statuses of one DiagnosticArray, by container name.

    Statuses are named ``<container>: <what>``; a group without a container status carrying the uptime is
    not a container's report (another node publishing on /diagnostics) and is left out.
    """
    groups: dict[str, dict[str, Status]] = {}
    for status in statuses:
        container, separator, what = status.name.partition(": ")
        if separator:
            groups.setdefault(container, {})[what] = parse_status(status)
    reports = {}
    for container, group in groups.items():
        own = group.pop(CONTAINER_STATUS, None)
        if own is not None and UPTIME in own.values:
            reports[container] = Report(float(own.values[UPTIME]), own, group)
    return reports


@dataclass(frozen=True)
class Rate:
    """A topic's message rate (Hz) and bandwidth (bytes/s) between two reports."""

    hz: float
    bytes_per_second: float


def topic_rate(before: Published | None, before_uptime: float, after: Published, after_uptime: float) -> Rate | None:
    """The rate between two reports' counts of one topic; None when they cannot be compared (a restart).

    The time is that between the last publishes the counts include, so that whole message periods are counted;
    before any publish, the earlier report's own time stands in.
    """
    before = before or Published(0, 0, None)
    if after.messages < before.messages:
        return None
    if after.messages == before.messages or after.age is None:
        return Rate(0.0, 0.0)
    start = before_uptime - (before.age if before.age is not None else 0.0)
    elapsed = (after_uptime - after.age) - start
    if elapsed <= 0:
        return None
    return Rate((after.messages - before.messages) / elapsed, (after.bytes - before.bytes) / elapsed)


def topic_rates(previous: Report | None, latest: Report, component: str) -> dict[str, Rate | None]:
    """Each topic of ``component`` in ``latest`` with its rate since ``previous`` (None: not yet known)."""
    now = latest.components[component].published
    if previous is None or previous.uptime >= latest.uptime or component not in previous.components:
        return {topic: None for topic in now}
    before = previous.components[component].published
    return {topic: topic_rate(before.get(topic), previous.uptime, counts, latest.uptime)
            for topic, counts in now.items()}


def human_rate(bytes_per_second: float) -> str:
    for unit, scale in (("GB/s", 1e9), ("MB/s", 1e6), ("kB/s", 1e3)):
        if bytes_per_second >= scale:
            return f"{bytes_per_second / scale:.1f} {unit}"
    return f"{bytes_per_second:.0f} B/s"


def human_disk(megabytes: str | None) -> str:
    if megabytes is None:
        return "-"
    value = float(megabytes)
    return f"{value / 1e3:.1f} GB" if value >= 1e3 else f"{value:.0f} MB"


@dataclass
class ContainerView:
    """One container as the view knows it: its ListNodes listing (or why not) and its last two reports."""

    name: str
    listed: list[tuple[int, str]] = field(default_factory=list)
    error: str | None = None
    previous: Report | None = None
    latest: Report | None = None

    def add(self, report: Report) -> None:
        """A new report; one from an earlier uptime (the container restarted) starts the history over."""
        restarted = self.latest is not None and report.uptime <= self.latest.uptime
        self.previous, self.latest = (None if restarted else self.latest), report

    def listing_is_stale(self) -> bool:
        """Whether the last report names other loaded components than the listing (loaded or unloaded since)."""
        if self.latest is None:
            return False
        reported = {name for name, status in self.latest.components.items() if "plugin" in status.values}
        return reported != {name for _, name in self.listed}


def _component_rows(view: ContainerView) -> list[tuple[str, ...]]:
    statuses = view.latest.components if view.latest is not None else {}
    names = [(str(uid), name) for uid, name in view.listed]
    listed = {name for _, name in names}
    names += [(status.values.get("unique_id", "?"), name) for name, status in statuses.items() if name not in listed]
    rows: list[tuple[str, ...]] = []
    for uid, name in names:
        status = statuses.get(name)
        if status is None:
            rows.append((uid, name, "-", "-", "-", "-", "-", "no report yet"))
            continue
        rates = topic_rates(view.previous, view.latest, name)  # type: ignore[arg-type]  # status implies latest
        own = (status.values.get(DROPPED, "-"), human_disk(status.values.get(FREE_DISK_MB)), status.text)
        if not rates:
            rows.append((uid, name, "-", "-", "-", *own))
        for index, topic in enumerate(sorted(rates)):
            rate = rates[topic]
            cells = ("-", "-") if rate is None else (f"{rate.hz:.1f}", human_rate(rate.bytes_per_second))
            rows.append(((uid, name) if index == 0 else ("", "")) + (topic, *cells)
                        + (own if index == 0 else ("", "", "")))
    return rows


def container_lines(view: ContainerView) -> list[str]:
    """One container: a heading line, then the table of its components and their topics."""
    if view.latest is None:
        heading = f"{view.name}  no /diagnostics report yet"
    else:
        own = view.latest.container
        heading = (f"{view.name}  {own.text}  executor {own.values.get('executor', '?')}  "
                   f"free disk {human_disk(own.values.get(FREE_DISK_MB))}  up {view.latest.uptime:.0f} s")
    if view.error:
        heading += f"  ({view.error})"
    return [heading, *format_table(HEADER, _component_rows(view))]


def render(views: Sequence[ContainerView]) -> list[str]:
    """Every container, one blank line apart."""
    lines: list[str] = []
    for view in views:
        lines += ([""] if lines else []) + container_lines(view)
    return lines
