"""``ipc-component record start | stop | split``: one recording across every container of the domain.

``start`` loads a recorder (``components::Recorder``, node ``record_<session>``) into every matching container,
on every computer DDS discovery reaches, and gives all of them one start instant, corrected by each container's
measured clock offset (see ipc_component.fleet_link). Each recorder subscribes at once but writes only the
messages received from that instant on (components/recorder/schedule.py), into ``<session>/<host>_<container>``
under its container's bag root, with the session's facts in ``custom_data`` (baglib.format.fleet_keys).
``--local-only`` (the default) records in each container only what that container publishes in-process, so no
topic crosses the network to be recorded. ``stop`` schedules the end the same way, waits for every bag to be
finalized, prints what each recorder wrote and unloads them; ``split`` schedules a split.

A container that does not answer is named and left out; the others record (``--all-or-nothing`` aborts instead).
Recorders keep to their schedule without the command: a ``--max-duration`` given at start ends the recording
even if the stop never reaches them (a network partition).
"""
from __future__ import annotations

import argparse
import fnmatch
import glob
import json
import re
import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Sequence

from baglib.format import fleet_keys
from ipc_component.recorder_lookup import PlacedRecorder, find_recorders, recorder_full_name, recorder_node
from ipc_component.ros_session import BUDGET, CALL_TIMEOUT, CliError, RosSession
from ipc_component.verb_arguments import add_verb, in_options, parameter_msgs

if TYPE_CHECKING:
    from ipc_component.fleet_link import ContainerLink, Fleet

RECORDER_PLUGIN = ("components", "components::Recorder")
SESSION_NAME = re.compile(r"^[A-Za-z0-9_]+$")
#: s: how long discovery watches the graph for containers (other computers answer later than local ones)
DISCOVERY = 1.5
#: Offsets above this (ms) are reported at start.
OFFSET_WARNING_MS = 5.0
#: s: how far ahead ``stop`` and ``split`` schedule their instant by default: time for the request to reach every
#: recorder before the instant, so that each cuts exactly there
STOP_AHEAD = 1.0
#: s: how long ``stop`` waits for the bags to be finalized after the stop instant
FINALIZE_TIMEOUT = 30.0
#: Parameters that select topics: when one is given, the recorder is not told to record all topics.
SELECTION = ("record.all_topics", "record.topics", "record.topic_types", "record.regex", "record.services",
             "record.all_services", "record.actions", "record.all_actions", "topics", "topic_names", "record_all")


def bag_directory(session: str, link: ContainerLink) -> str:
    """``<session>/<host>_<container>``, the container's name without its slashes."""
    return f"{session}/{link.host}_{link.name.strip('/').replace('/', '_')}"


def upload_uri(uri: str, session: str) -> str:
    """``--upload``: each recorder uploads under ``PREFIX/<session>``, so its bag's keys are
    ``PREFIX/<session>/<host>_<container>/<file>``: two robots, or two sessions, never share a key."""
    from baglib.upload.location import parse_s3_uri

    try:
        return parse_s3_uri(uri, "--upload").child(session).uri
    except ValueError as error:
        raise CliError(str(error)) from None


def instant_ns(args: argparse.Namespace, default_in: float) -> int:
    """The scheduled instant on this computer's clock: ``--at``, else now + ``--in``."""
    if args.at is not None:
        return round(args.at * 1e9)
    return time.time_ns() + round((default_in if args.in_seconds is None else args.in_seconds) * 1e9)


#: ``record start`` options passed on to each recorder when given: (option, recorder parameter, conversion).
FLAG_PARAMETERS: list[tuple[str, str, Callable[[Any], Any]]] = [
    ("max_duration", "record.max_duration", float),
    ("compress", "record.compress", str),
    ("compress_regex", "record.compress_regex", str),
    ("max_rates", "record.max_rates", list),
    ("repeat_transient_local", "record.repeat_transient_local", list),
    ("repeat_all_transient_local", "record.repeat_all_transient_local", lambda value: value),
    ("max_cache_duration", "storage.max_cache_duration", float),
    ("actions", "record.actions", list),
    ("all_actions", "record.all_actions", bool),
    ("exclude_actions", "record.exclude_actions", list),
]


def _options_given(args: argparse.Namespace) -> dict[str, str]:
    """The recorder parameters this ``record start`` set from its options, by option (for the recorders' errors)."""
    given = {parameter: f"--{option.replace('_', '-')}" for option, parameter, _ in FLAG_PARAMETERS
             if getattr(args, option)}
    uploads = {"upload.uri": "--upload", "upload.endpoint_url": "--upload-endpoint-url"}
    return given | {parameter: option for parameter, option in uploads.items() if args.upload}


def _parameters(session: str, link: ContainerLink, start_ns: int, args: argparse.Namespace) -> list[Any]:
    from rclpy.parameter import Parameter

    given = parameter_msgs(args.parameters, "parameter")
    names = {p.name for p in given}
    offset = link.offset
    assert offset is not None
    custom = {fleet_keys.SESSION: session, fleet_keys.HOST: link.host, fleet_keys.CONTAINER: link.name,
              fleet_keys.START_NS: str(start_ns), fleet_keys.CLOCK_OFFSET_NS: str(offset.offset_ns),
              fleet_keys.CLOCK_OFFSET_UNCERTAINTY_NS: str(offset.uncertainty_ns)}
    ours = {"storage.uri": bag_directory(session, link),
            "record.start_at": (start_ns + offset.offset_ns) / 1e9,
            "record.local_only": args.local_only,
            "storage.custom_data": [f"{key}={value}" for key, value in custom.items()]}
    for option, parameter, convert in FLAG_PARAMETERS:
        value = getattr(args, option)
        if value:
            ours[parameter] = convert(value)
    if args.upload:
        ours["upload.uri"] = upload_uri(args.upload, session)
        if args.upload_endpoint_url:
            ours["upload.endpoint_url"] = args.upload_endpoint_url
    if not names & set(SELECTION) and not (args.actions or args.all_actions):
        ours["record.all_topics"] = True
    clash = names & set(ours)
    if clash:
        raise CliError(f"-p {', '.join(sorted(clash))}: set by the fleet session itself")
    return [Parameter(name, value=value).to_parameter_msg() for name, value in ours.items()] + given


def _select(containers: Sequence[str], patterns: Sequence[str]) -> tuple[list[str], list[str]]:
    """The containers matching ``patterns`` (all without), and the names given exactly that are not there."""
    if not patterns:
        return list(containers), []
    missing = [p for p in patterns if not glob.has_magic(p) and p not in containers]
    return [c for c in containers if any(fnmatch.fnmatchcase(c, p) for p in patterns)], missing


def _discover(ros: RosSession, spin_time: float, named: Sequence[str]) -> dict[str, list[tuple[int, str]]]:
    """Every container of the domain with its components (None for a container that did not list them); those
    ``named`` exactly (not by a pattern) are waited for past ``spin_time``, up to BUDGET more."""
    from ipc_component.container_discovery import list_containers

    start = time.monotonic()
    listings = list_containers(ros.node, ros.executor, deadline=start + BUDGET + spin_time,
                               discovery_until=start + spin_time,
                               awaited=[name for name in named if not glob.has_magic(name)])
    return {listing.container: (None if listing.error else listing.components) for listing in listings}


def _print_rows(header: Sequence[str], rows: list[Sequence[str]]) -> None:
    widths = [max(len(str(row[i])) for row in [header, *rows]) for i in range(len(header))]
    for row in [header, *rows]:
        print("  ".join(str(cell).ljust(width) for cell, width in zip(row, widths)).rstrip())


def _offset_text(link: ContainerLink) -> str:
    offset = link.offset
    return "?" if offset is None else f"{offset.offset_ns / 1e6:+.2f}±{offset.uncertainty_ns / 1e6:.2f} ms"


# --- start ----------------------------------------------------------------------------------------------
def run_start(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    from composition_interfaces.srv import LoadNode

    session = args.session or time.strftime("fleet_%Y%m%d_%H%M%S")
    if not SESSION_NAME.match(session):
        raise CliError(f"Invalid --session '{session}': use letters, digits and '_'")
    parameter_msgs(args.parameters, "parameter")  # a malformed -p is refused before any ROS traffic
    if args.upload:
        upload_uri(args.upload, session)  # so is a bad --upload
    with RosSession(ros_args) as ros:
        found = _discover(ros, args.spin_time, args.containers)
        containers, missing = _select(sorted(found), args.containers)
        if not containers:
            raise CliError("No container found" + (f" matching {' '.join(args.containers)}" if args.containers else "")
                           + f"\n    {ros.where_searched()}")
        busy = [c for c in containers
                if any(name == recorder_full_name(c, session) for _id, name in found[c] or [])]
        if busy:
            raise CliError(f"Session '{session}' is already recording in {', '.join(busy)}")
        fleet = ros.fleet([*containers, *missing])
        for link in fleet.links[len(containers):]:
            link.error = "not found on the ROS graph"
        fleet.connect(time.monotonic() + BUDGET)
        fleet.measure_offsets(time.monotonic() + BUDGET)
        if args.all_or_nothing and not all(link.ok for link in fleet.links):
            _report_failures(fleet.links)
            raise CliError("Not starting: --all-or-nothing and a container did not answer")
        start_ns = instant_ns(args, default_in=2.0)
        ros.graph_changed()
        calls = {link.name: (link.load, LoadNode.Request(
            package_name=RECORDER_PLUGIN[0], plugin_name=RECORDER_PLUGIN[1], node_name=recorder_node(session),
            node_namespace=link.name,
            parameters=_parameters(session, link, start_ns, args),
            extra_arguments=parameter_msgs(["use_intra_process_comms:=true"], "extra argument")))
            for link in fleet.answering}
        replies = fleet.call_all(calls, time.monotonic() + CALL_TIMEOUT)
        for link in fleet.answering:
            reply = replies.get(link.name)
            if reply is None:
                link.error = "no reply to the load request"
            elif not reply.success:
                link.error = f"recorder not loaded: {in_options(reply.error_message, _options_given(args))}"
        recording = fleet.answering
        if args.all_or_nothing and len(recording) != len(fleet.links):
            _unload(fleet, [(link, replies[link.name].unique_id) for link in recording])
            _report_failures(fleet.links)
            raise CliError("Aborted: --all-or-nothing and a recorder was not loaded everywhere (unloaded again)")
    if not recording:  # nothing to announce: only why
        _report_failures(fleet.links)
        raise CliError(f"Session {session} not started: no container records")
    _report_start(session, start_ns, fleet.links)
    return 0 if len(recording) == len(fleet.links) else 2


def _unload(fleet: Fleet, components: Sequence[tuple[ContainerLink, int]]) -> None:
    """Unload each (container, unique id) at once, waiting for the replies (at most CALL_TIMEOUT)."""
    from composition_interfaces.srv import UnloadNode

    fleet.call_all({f"{link.name}#{uid}": (link.unload, UnloadNode.Request(unique_id=uid)) for link, uid in components},
                   time.monotonic() + CALL_TIMEOUT)


def _report_failures(links: Sequence[ContainerLink]) -> None:
    """Each container that does not take part, and why, on stderr."""
    for link in links:
        if link.error:
            print(f"Not recording in {link.name}: {link.error}", file=sys.stderr)


def _report_start(session: str, start_ns: int, links: Sequence[ContainerLink]) -> None:
    wait = (start_ns - time.time_ns()) / 1e9
    print(f"Session {session}: recording from {time.strftime('%H:%M:%S', time.localtime(start_ns / 1e9))}"
          f".{start_ns % 1_000_000_000 // 1_000_000:03d} ({'in' if wait >= 0 else 'since'} {abs(wait):.1f} s)")
    rows = [(link.host, link.name, _offset_text(link), _bag_path(link, bag_directory(session, link)))
            for link in links if link.ok]
    _print_rows(("HOST", "CONTAINER", "CLOCK OFFSET", "BAG"), rows)
    for link in links:
        offset = link.offset
        if link.ok and offset is not None and abs(offset.offset_ns) / 1e6 > OFFSET_WARNING_MS:
            print(f"Warning: the clock of {link.host} ({link.name}) is {offset.offset_ns / 1e6:+.1f} ms off this "
                  f"computer's (more than {OFFSET_WARNING_MS:g} ms); the start is corrected for it")
    _report_failures(links)


def _bag_path(link: ContainerLink, relative: str) -> str:
    return f"{link.bag_root.rstrip('/')}/{relative}" if link.bag_root else relative


# --- stop and split -------------------------------------------------------------------------------------
@dataclass
class _Recorders:
    """The recorders a ``stop`` or ``split`` addresses, their containers (connected, with their clock offsets), and
    why a recorder did not do what was asked (by node name)."""

    fleet: Fleet
    placed: list[PlacedRecorder]
    errors: dict[str, str] = field(default_factory=dict)

    def link(self, recorder: PlacedRecorder) -> ContainerLink:
        return next(link for link in self.fleet.links if link.name == recorder.container)

    @property
    def live(self) -> list[PlacedRecorder]:
        """The recorders whose container answers and that have not failed."""
        return [r for r in self.placed if self.link(r).ok and r.node not in self.errors]

    @property
    def ok(self) -> bool:
        return not self.errors and all(link.ok for link in self.fleet.links)

    def report_failures(self) -> None:
        _report_failures(self.fleet.links)
        for node, error in self.errors.items():
            print(f"{node}: {error}", file=sys.stderr)


def _session_recorders(ros: RosSession, args: argparse.Namespace) -> _Recorders:
    """The recorders of ``--session`` (of every fleet session without it), in as many sessions and containers as
    there are, with their containers connected and their clock offsets measured."""
    placed = find_recorders(ros, args.spin_time, args.session, fleet_only=True)
    fleet = ros.fleet(sorted({recorder.container for recorder in placed}))
    fleet.connect(time.monotonic() + BUDGET)
    fleet.measure_offsets(time.monotonic() + BUDGET)
    return _Recorders(fleet, placed)


def _set_on_all(recorders: _Recorders, instant_parameter: str, instant: int,
                custom_data: dict[str, str] | None = None) -> None:
    """Set ``instant_parameter`` on every recorder to ``instant`` on its container's clock (this computer's clock
    plus the offset just measured); with ``custom_data``, add those pairs and the offset used to the bag."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    fleet = recorders.fleet
    calls = {}
    for recorder in recorders.live:
        link = recorders.link(recorder)
        offset = link.offset.offset_ns if link.offset else 0
        parameters = [Parameter(instant_parameter, value=(instant + offset) / 1e9)]
        if custom_data is not None:
            pairs = {**custom_data, fleet_keys.STOP_CLOCK_OFFSET_NS: str(offset)}
            parameters.append(Parameter("storage.custom_data", value=[f"{k}={v}" for k, v in pairs.items()]))
        calls[recorder.node] = (fleet.parameter_client(link, recorder.node),
                                SetParameters.Request(parameters=[p.to_parameter_msg() for p in parameters]))
    replies = fleet.repeat_all(calls, time.monotonic() + BUDGET)
    if time.time_ns() > instant:
        print(f"Warning: the instant passed {(time.time_ns() - instant) / 1e6:.0f} ms before every recorder had it: "
              "a recorder writes what it received until then (schedule it ahead with --in)")
    for node in calls:
        reply = replies.get(node)
        if reply is None:
            recorders.errors[node] = "the recorder did not answer"
        elif not all(result.successful for result in reply.results):
            recorders.errors[node] = "; ".join(result.reason for result in reply.results if not result.successful)


def run_stop(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    with RosSession(ros_args) as ros:
        recorders = _session_recorders(ros, args)
        stop_ns = instant_ns(args, default_in=STOP_AHEAD)
        _set_on_all(recorders, "record.stop_at", stop_ns, {fleet_keys.STOP_NS: str(stop_ns)})
        finals = _wait_finalized(recorders, stop_ns)
        ros.graph_changed()
        _unload(recorders.fleet, [(recorders.link(r), r.unique_id) for r in recorders.placed if r.node in finals])
    rows = []
    for recorder in recorders.placed:
        final = finals.get(recorder.node)
        if final is None:
            continue
        topics = final["topics"].values()
        rows.append((recorders.link(recorder).host, recorder.container, str(sum(t["written"] for t in topics)),
                     f"{final['bytes_written'] / 1e6:.1f} MB", str(sum(t["dropped"] for t in topics)),
                     final["bag"] + (f" (error: {final['error']})" if final["error"] else "")))
    if rows:
        _print_rows(("HOST", "CONTAINER", "MESSAGES", "BYTES", "DROPS", "BAG"), rows)
    recorders.report_failures()
    return 0 if recorders.ok else 1


def _wait_finalized(recorders: _Recorders, stop_ns: int) -> dict[str, dict]:
    """Poll every recorder's ~/get_stats until its bag is finalized; the final counts per recorder node."""
    from std_srvs.srv import Trigger

    fleet = recorders.fleet
    deadline = time.monotonic() + max(0.0, (stop_ns - time.time_ns()) / 1e9) + FINALIZE_TIMEOUT
    finals: dict[str, dict] = {}
    while time.monotonic() < deadline:
        pending = [recorder for recorder in recorders.live if recorder.node not in finals]
        if not pending:
            break
        calls = {r.node: (fleet.component_client(recorders.link(r), Trigger, f"{r.node}/get_stats"), Trigger.Request())
                 for r in pending}
        for node, reply in fleet.repeat_all(calls, min(deadline, time.monotonic() + BUDGET)).items():
            stats = json.loads(reply.message)
            if not stats["recording"] and stats["finished"]:
                finals[node] = stats["finished"][-1]
        fleet.spin_until(lambda: False, min(deadline, time.monotonic() + 0.2))
    for recorder in recorders.live:
        if recorder.node not in finals:
            recorders.errors[recorder.node] = "the bag was not finalized in time"
    return finals


def run_split(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    with RosSession(ros_args) as ros:
        recorders = _session_recorders(ros, args)
        split_ns = instant_ns(args, default_in=STOP_AHEAD)
        _set_on_all(recorders, "record.split_at", split_ns)
    for recorder in recorders.live:
        print(f"Split scheduled in {recorder.container} ({recorders.link(recorder).host}), session "
              f"{recorder.session}")
    recorders.report_failures()
    return 0 if recorders.ok else 1


# --- the command line -----------------------------------------------------------------------------------
def _add_timing(p: argparse.ArgumentParser, default_in: float) -> None:
    when = p.add_mutually_exclusive_group()
    when.add_argument("--in", dest="in_seconds", type=float, default=None, metavar="SECONDS",
                      help=f"the instant, in seconds from now (default {default_in:g})")
    when.add_argument("--at", type=float, default=None, metavar="EPOCH_SECONDS",
                      help="the instant, in seconds since the epoch on this computer's clock")


def add_record_parser(verbs: Any) -> Any:
    """Add ``record`` and its verbs start, stop and split; returns its sub-parsers, for more verbs."""
    p = add_verb(verbs, "record", "Record every container of the domain as one (fleet recording)",
                 "start loads a recorder into every matching container, on every computer DDS discovery "
                 "reaches, and gives them all one start instant, corrected by each container's measured clock "
                 "offset. Each writes <session>/<host>_<container> under its container's bag root. stop "
                 "schedules the end the same way, waits for every bag to be finalized, prints what each "
                 "recorder wrote and unloads them; split schedules a split; status shows every recorder.")
    record_verbs = p.add_subparsers(dest="record_verb", title="commands")
    record_verbs.required = True
    p = add_verb(record_verbs, "start", "Load a recorder into every container; all start at one instant")
    p.add_argument("containers", nargs="*", metavar="CONTAINER_PATTERN",
                   help="full container names or fnmatch patterns (default: every container)")
    p.add_argument("--session", help="session name (default: fleet_<date>_<time>)")
    _add_timing(p, 2.0)
    p.add_argument("--local-only", action=argparse.BooleanOptionalAction, default=True,
                   help="record in each container only what it publishes in-process (default: yes)")
    p.add_argument("--max-duration", type=float, default=0.0, metavar="SECONDS",
                   help="every recorder stops this long after the start even if no stop reaches it")
    p.add_argument("--all-or-nothing", action="store_true",
                   help="abort (and unload what was loaded) unless every container records")
    p.add_argument("--compress", metavar="CODEC",
                   help="record image topics compressed: jpeg, png, h264, h265, av1 or an FFmpeg encoder name; "
                        "each recorder loads an ImageEncoder beside it (record.compress)")
    p.add_argument("--compress-regex", metavar="REGEX",
                   help="the image topics to compress (default: every sensor_msgs/msg/Image topic)")
    p.add_argument("--max-rates", nargs="+", metavar="TOPIC_OR_REGEX:RATE",
                   help="per-topic rate limits in messages per second (record.max_rates), e.g. '/lidar.*:2'")
    p.add_argument("--repeat-transient-local", nargs="+", metavar="TOPIC[=DEPTH]",
                   help="write these latched topics' last DEPTH (1) messages again at the start of every split "
                        "file and snapshot (record.repeat_transient_local, as ros2 bag record's)")
    p.add_argument("--repeat-all-transient-local", nargs="?", type=int, const=1, default=0, metavar="DEPTH",
                   help="the same for every topic recorded transient_local (record.repeat_all_transient_local)")
    p.add_argument("--max-cache-duration", type=float, default=0.0, metavar="SECONDS",
                   help="snapshot mode (-p storage.snapshot_mode:=true): the ring holds at most the last SECONDS "
                        "(storage.max_cache_duration)")
    p.add_argument("--actions", nargs="+", metavar="ACTION",
                   help="record these actions: feedback, status and their services' events (record.actions, as "
                        "ros2 bag record's); without a topic selection, only them")
    p.add_argument("--all-actions", action="store_true", help="record every action (record.all_actions)")
    p.add_argument("--exclude-actions", nargs="+", metavar="ACTION",
                   help="do not record these actions (record.exclude_actions)")
    p.add_argument("--upload", metavar="s3://BUCKET/PREFIX",
                   help="upload every finished file to S3-compatible storage, under PREFIX/<session>/<host>_"
                        "<container>/ (upload.uri; credentials from each container's AWS environment)")
    p.add_argument("--upload-endpoint-url", metavar="URL",
                   help="the S3-compatible store to upload to (upload.endpoint_url; default: the AWS configuration)")
    p.add_argument("-p", "--parameter", action="append", dest="parameters",
                   help="a recorder parameter, in the 'name:=value' form")
    p.add_argument("--spin-time", type=float, default=DISCOVERY, help="seconds to discover containers")
    p.set_defaults(handler=run_start)
    for verb, handler, what in (("stop", run_stop, "Stop the session's recorders at one instant and unload them"),
                                ("split", run_split, "Split every bag of the session at one instant")):
        p = add_verb(record_verbs, verb, what)
        p.add_argument("--session", help="session name (default: every fleet session)")
        _add_timing(p, STOP_AHEAD)
        p.add_argument("--spin-time", type=float, default=DISCOVERY, help="seconds to discover containers")
        p.set_defaults(handler=handler)
    return record_verbs
