"""``ipc-component``: the ``ros2 component`` command line for rclpy component containers.

Verbs ``list``, ``load``, ``unload`` and ``types`` behave like their ``ros2 component`` counterparts: the
same output lines, the same failure messages (on stderr) and exit code 1 on failure. Differences, all on
the side of not hanging and of clearer errors:

* discovery and listing share one 5 s budget; loading and unloading wait at most 60 s for each reply, then until
  the graph has been quiet for 0.3 s (at most 3 s) before the command ends (docs/limitations.md, Fast DDS);
* ``list`` without a container name watches the graph for 0.6 s (``--spin-time``; ros2cli: 0.5 s) from the
  moment its participant exists, then ends as soon as every container found has answered;
* ``--log-level`` takes a level name (DEBUG, INFO, WARN, ERROR, FATAL; any case) or its number;
* a ``-p``/``-e`` argument without ``:=``, a ``-r`` rule without ``:=`` and a unique id that is not a
  non-negative integer are refused before anything is sent, with exit code 1;
* ``unload`` tries every id given and reports each failure (ros2 component stops at the first);
* a search that finds no container says which ROS_DOMAIN_ID and discovery range it searched, and ``load``
  prints the warning a successful load may carry (parameters the component does not declare).

ROS arguments may follow ``--ros-args`` (ended by ``--``) and apply to the command's own node, which is
hidden (``_ipc_component_<pid>``) so that it is never taken for a container.
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from typing import Sequence

from ipc_component import (bag_burst, bag_convert, bag_export, bag_merge, bag_play, bag_remote, bag_upload, create,
                           record_fleet, record_status, top)
from ipc_component.ros_session import BUDGET, CliError, RosSession, end_ros
from ipc_component.verb_arguments import (LOG_LEVEL_HELP, add_verb, parameter_msgs, parse_log_level,
                                          parse_unique_id, remap_rules)

# s: how long ``list`` without a container watches the graph. This project's containers re-announce every
# 0.25 s (component_container.discovery_profile), so even a lost first exchange is over in ~0.45 s; a
# container announcing at Fast DDS's default 3 s may need ``--spin-time 3.5``.
LIST_DISCOVERY = 0.6

def _capitalized(text: str) -> str:
    # ros2component capitalizes the container's message; only the first letter is changed here, so that
    # names and exception types quoted in the message keep their case.
    return text[:1].upper() + text[1:]


# --- list -----------------------------------------------------------------------------------------------
def run_list(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    from ipc_component.container_discovery import list_containers

    if args.spin_time < 0:
        raise CliError(f"Invalid --spin-time {args.spin_time:g}: must not be negative")
    start = time.monotonic()
    with RosSession(ros_args) as ros:
        listings = list_containers(
            ros.node, ros.executor, deadline=start + BUDGET, discovery_until=time.monotonic() + args.spin_time,
            container=args.container_node_name, list_components=not args.containers_only)
        where_searched = ros.where_searched()
    lines = []
    if args.container_node_name is not None:
        if not listings:
            raise CliError(f"Unable to find container node '{args.container_node_name}'\n    {where_searched}")
        listing = listings[0]
        if not args.containers_only:
            if listing.error:
                raise CliError(f"{listing.error} when listing components in {listing.container}")
            lines += [f"{uid}  {name}" for uid, name in listing.components]
    else:
        for listing in listings:
            lines.append(listing.container)
            if args.containers_only:
                continue
            if listing.error:
                lines.append(f"{listing.error} when listing components")
                continue
            lines += [f"  {uid}  {name}" for uid, name in listing.components]
        if not listings:  # stdout stays empty, as with ros2 component list; the hint goes to stderr
            print(f"No container found\n    {where_searched}", file=sys.stderr, flush=True)
    _print_lines(lines)
    return 0


# --- load -----------------------------------------------------------------------------------------------
def run_load(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    from composition_interfaces.srv import LoadNode

    container = args.container_node_name
    # Everything is checked before any ROS traffic, so that a typo costs no waiting.
    request = LoadNode.Request(
        package_name=args.package_name, plugin_name=args.plugin_name,
        node_name=args.node_name or "", node_namespace=args.node_namespace or "",
        log_level=parse_log_level(args.log_level), remap_rules=remap_rules(args.remap_rules),
        parameters=parameter_msgs(args.parameters, "parameter"),
        extra_arguments=parameter_msgs(args.extra_arguments, "extra argument"))
    start = time.monotonic()
    with RosSession(ros_args) as ros:
        client = ros.container_client(LoadNode, container, "load_node", start + BUDGET)
        ros.graph_changed()
        try:
            response = ros.call(client, request, container)
        except CliError as exc:
            raise CliError(f"Failed to load component: {exc}") from None
    if not response.success:
        raise CliError(f"Failed to load component: {_capitalized(response.error_message)}")
    if response.error_message:  # loaded, with a warning (this project's containers: undeclared parameters)
        print(f"Warning: {response.error_message}", file=sys.stderr, flush=True)
    if args.quiet:
        _print_lines([f"{response.unique_id}  {response.full_node_name}"])
    else:
        _print_lines([f"Loaded component {response.unique_id} into '{container}' container node as "
                      f"'{response.full_node_name}'"])
    return 0


# --- unload ---------------------------------------------------------------------------------------------
def run_unload(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    from composition_interfaces.srv import UnloadNode

    container = args.container_node_name
    unique_ids = [parse_unique_id(text) for text in args.component_uid]
    start = time.monotonic()
    failed = 0
    with RosSession(ros_args) as ros:
        client = ros.container_client(UnloadNode, container, "unload_node", start + BUDGET)
        ros.graph_changed()
        for uid in unique_ids:  # every id is tried: one that fails does not keep the others loaded
            try:
                response = ros.call(client, UnloadNode.Request(unique_id=uid), container)
                reason = None if response.success else response.error_message
            except CliError as exc:
                reason = str(exc)
            if reason is not None:
                failed += 1
                sys.stdout.flush()
                print(f"Failed to unload component {uid} from '{container}' container node\n"
                      f"    {_capitalized(reason)}", file=sys.stderr, flush=True)
                continue
            _print_lines([str(uid) if args.quiet else
                          f"Unloaded component {uid} from '{container}' container node"])
    return 1 if failed else 0


# --- types ----------------------------------------------------------------------------------------------
def run_types(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    # Only the local installation is consulted: no ROS communication, so no rclpy session is needed.
    from component_container.plugin_registry import ENTRY_POINT_GROUP, PluginRegistry

    plugins = PluginRegistry().plugins_by_package()
    if args.package_name is not None:
        if args.package_name not in plugins:
            raise CliError(f"Unable to find package '{args.package_name}': it is not installed in the Python "
                           f"environment {sys.prefix} (no entry point of the group '{ENTRY_POINT_GROUP}' "
                           "belongs to it)")
        _print_lines(plugins[args.package_name])
        return 0
    lines = []
    for package, names in plugins.items():
        lines.append(package)
        lines += [f"  {name}" for name in names]
    _print_lines(lines)
    return 0


# --- bag info -------------------------------------------------------------------------------------------
def run_bag_info(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    # Reads files only, like `ros2 bag info`: no rclpy session.
    from baglib.tools.info import BagInfoError, format_bag_info

    if args.topic_name and args.verbose:
        print("Warning! You have set both the '-t' and '-v' parameters. The '-t' parameter will be ignored.",
              flush=True)
    if bag_remote.is_remote(args.bag_path):
        print(bag_remote.remote_info(args), flush=True)
        return 0
    try:
        print(format_bag_info(args.bag_path, args.sort, args.verbose, args.topic_name), flush=True)
    except BagInfoError as exc:
        raise CliError(str(exc)) from exc
    return 0


def run_bag_recover(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    """Recover a bag a crash left unfinished; exit 1 unless the result is readable."""
    from baglib.tools.repair import recover_bag

    report = recover_bag(args.bag_path, args.output)
    print(report.text(), flush=True)
    if not report.readable:
        raise CliError(f"cannot recover {args.bag_path}: {report.error}")
    return 0


# --- command line ---------------------------------------------------------------------------------------
def _print_lines(lines: Sequence[str]) -> None:
    if lines:
        print("\n".join(lines), flush=True)


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """Separate ``--ros-args ... [--]`` sections from the command's own arguments.

    rclpy's ``remove_ros_args`` cannot be used: it also takes bare ``name:=value`` words for (deprecated)
    remap rules, which are exactly what ``-r``/``-p``/``-e`` take here.
    """
    own: list[str] = []
    ros: list[str] = []
    in_ros = False
    for word in argv:
        if word == "--ros-args":
            in_ros = True
            ros.append(word)
        elif in_ros and word == "--":
            in_ros = False
        elif in_ros:
            ros.append(word)
        else:
            own.append(word)
    return own, ros


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ipc-component", description="Various component related sub-commands (like ros2 component).")
    verbs = parser.add_subparsers(dest="verb", title="commands",
                                  description="Call 'ipc-component <command> -h' for more detailed usage.")
    verbs.required = True

    p = add_verb(verbs, "list", "Output a list of running containers and components")
    p.add_argument("container_node_name", nargs="?", default=None,
                   help="Name of the container node to list components from")
    p.add_argument("--containers-only", action="store_true", help="List found containers nodes only")
    p.add_argument("--spin-time", type=float, default=LIST_DISCOVERY,
                   help=f"Seconds to watch the graph for containers when no container is named "
                        f"(default {LIST_DISCOVERY:g}; everything stays within a {BUDGET:g} s budget)")
    p.set_defaults(handler=run_list)

    p = add_verb(verbs, "load", "Load a component into a container node")
    p.add_argument("container_node_name", help="Container node name to load component into")
    p.add_argument("package_name", help="Name of the package where the component is to be found")
    p.add_argument("plugin_name", help="Type name of the component to be loaded")
    p.add_argument("-n", "--node-name", help="Component node name")
    p.add_argument("--node-namespace", help="Component node namespace")
    p.add_argument("--log-level", help=f"Component node log level: {LOG_LEVEL_HELP}")
    p.add_argument("-r", "--remap-rule", action="append", dest="remap_rules",
                   help="Component node remapping rules, in the 'from:=to' form")
    p.add_argument("-p", "--parameter", action="append", dest="parameters",
                   help="Component node parameters, in the 'name:=value' form")
    p.add_argument("-e", "--extra-argument", action="append", dest="extra_arguments",
                   help="Extra arguments for the container, in the 'name:=value' form")
    p.add_argument("-q", "--quiet", action="store_true", help="Only print component unique IDs and names")
    p.set_defaults(handler=run_load)

    p = add_verb(verbs, "unload", "Unload components from a container node",
                 "Every id given is tried; each failure is reported, and the exit status is 1 if any failed.")
    p.add_argument("container_node_name", help="Container node name to unload component from")
    p.add_argument("component_uid", nargs="+", help="Unique ID of the component to be unloaded")
    p.add_argument("-q", "--quiet", action="store_true", help="Only print component unique IDs")
    p.set_defaults(handler=run_unload)

    p = add_verb(verbs, "types", "Output a list of components registered in this installation",
                 "They are the entry points of the group rclpy_components in this Python environment.")
    p.add_argument("package_name", nargs="?", default=None,
                   help="Package name to look for registered components in")
    p.set_defaults(handler=run_types)

    p = add_verb(verbs, "create", "Create a new package of rclpy components (like ros2 pkg create)",
                 "It holds pyproject.toml with the entry point, a package with one component class, and a "
                 "README.")
    create.add_arguments(p)
    p.set_defaults(handler=create.run_create)

    p = add_verb(verbs, "top", "A live view of the containers: components, topic rates, drops, free disk",
                 "Built from their /diagnostics reports and ListNodes, redrawn once a second (q or Ctrl-C "
                 "quits); one plain-text snapshot with --once or when the output is not a terminal.")
    top.add_arguments(p)

    record_verbs = record_fleet.add_record_parser(verbs)
    record_status.add_arguments(record_verbs)

    p = add_verb(verbs, "bag", "Inspect, repair, merge, play and export rosbag2 bags (what ros2 bag offers)")
    bag_verbs = p.add_subparsers(dest="bag_verb", title="commands")
    bag_verbs.required = True
    p = add_verb(bag_verbs, "info", "Print information about a bag (like ros2 bag info)")
    p.add_argument("bag_path", help="Bag directory (with metadata.yaml), or a single .mcap / .db3 file; or "
                                    "s3://BUCKET/PREFIX/BAG, or s3://.../FILE.mcap, in S3-compatible storage")
    p.add_argument("--endpoint-url", default="", help=bag_remote.ENDPOINT_HELP)
    p.add_argument("-t", "--topic-name", action="store_true", help="Only display topic names.")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="Display request/response information for services and actions and each topic's size "
                        "contribution (reads every message once)")
    p.add_argument("--sort", default="name", choices=("name", "type", "count"),
                   help="Configuration for sorting of output. By default sorts by topic name - use this argument "
                        "to override.")
    p.set_defaults(handler=run_bag_info)
    recover = ("Keep every intact record (MCAP) or committed row (SQLite3) of every file, rebuild indexes and "
               "summaries, regenerate metadata.yaml, and report what was cut. Crash-safe: files are replaced "
               "only once their repaired version is on disk.")
    for verb, summary in (("recover", "Make a bag a crash left unfinished readable again"),
                          ("reindex", "The same as recover, under the name ros2 bag users know")):
        p = add_verb(bag_verbs, verb, summary, recover)
        p.add_argument("bag_path", help="Bag directory (metadata.yaml may be missing)")
        p.add_argument("-o", "--output", default=None,
                       help="Write the recovered bag to this new directory instead of in place")
        p.set_defaults(handler=run_bag_recover)
    bag_merge.register(bag_verbs)
    bag_convert.register(bag_verbs)
    bag_export.register(bag_verbs)
    bag_upload.register(bag_verbs)
    bag_remote.register(bag_verbs)
    p = add_verb(bag_verbs, "play", "Play back bags (like ros2 bag play)",
                 "Several bags play as one timeline.")
    bag_play.add_arguments(p)
    p.set_defaults(handler=bag_play.run_bag_play)
    p = add_verb(bag_verbs, "burst", "Publish a bag's messages as fast as possible (like ros2 bag burst)",
                 "Starts a player paused and bursts the next --num-messages messages (0: the whole bag), "
                 "their timing ignored; then it stays paused until Ctrl-C, as ros2 bag burst does.")
    bag_burst.add_arguments(p)
    p.set_defaults(handler=bag_burst.run_bag_burst)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    try:
        try:
            status = _run(sys.argv[1:] if argv is None else argv)
        finally:
            sys.stdout.flush()  # a closed pipe shows here (after -h too), not in Python's handler at exit
    except KeyboardInterrupt:
        status = 130
    except BrokenPipeError:
        status = _reader_gone()
    return end_ros(status)


def _run(argv: Sequence[str]) -> int:
    own, ros_args = split_ros_args(argv)
    args = build_parser().parse_args(own)
    try:
        return args.handler(args, ros_args)
    except CliError as exc:
        sys.stdout.flush()
        print(exc, file=sys.stderr, flush=True)
        return 1


def _reader_gone() -> int:
    """Stop quietly when the reader of the output went away (``bag info ... | head``), as ``cat`` does.

    The exit status is the shell's for a command ended by SIGPIPE (128 + 13). Python would try to flush stdout
    once more at exit and report that failure too, so stdout is pointed at /dev/null first.
    """
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return 128 + signal.SIGPIPE


if __name__ == "__main__":
    sys.exit(main())
