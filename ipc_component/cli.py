"""``ipc-component``: the ``ros2 component`` command line for rclpy component containers.

Verbs ``list``, ``load``, ``unload`` and ``types`` behave like their ``ros2 component`` counterparts: the
same output lines, the same failure messages (on stderr) and exit code 1 on failure. Differences, all on
the side of not hanging and of clearer errors:

* discovery and listing share one 5 s budget; loading and unloading wait at most 60 s for each reply;
* ``list`` without a container name watches the graph for 0.6 s (``--spin-time``; ros2cli: 0.5 s) from the
  moment its participant exists, then ends as soon as every container found has answered;
* ``--log-level`` takes a level name (DEBUG, INFO, WARN, ERROR, FATAL; any case) or its number;
* a ``-p``/``-e`` argument without ``:=``, a ``-r`` rule without ``:=`` and a unique id that is not a
  non-negative integer are refused before anything is sent, with exit code 1.

ROS arguments may follow ``--ros-args`` (ended by ``--``) and apply to the command's own node, which is
hidden (``_ipc_component_<pid>``) so that it is never taken for a container.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any, Callable, Sequence

from ipc_component import bag_merge, bag_play

BUDGET = 5.0             # s: discovery and listing, and waiting for a container's service
# s: how long ``list`` without a container watches the graph. This project's containers re-announce every
# 0.25 s (component_container.discovery_profile), so even a lost first exchange is over in ~0.45 s; a
# container announcing at Fast DDS's default 3 s may need ``--spin-time 3.5``.
LIST_DISCOVERY = 0.6
CALL_TIMEOUT = 60.0      # s: waiting for a LoadNode / UnloadNode reply (component constructors may be slow)
GONE_GRACE = 2.0         # s: a container whose service stays absent this long while we wait has left

LOG_LEVELS = {"DEBUG": 10, "INFO": 20, "WARN": 30, "WARNING": 30, "ERROR": 40, "FATAL": 50}
LOG_LEVEL_HELP = "DEBUG, INFO, WARN, ERROR or FATAL (any case), or 10, 20, 30, 40 or 50"
UINT64_MAX = 2**64 - 1
INT64_MIN, INT64_MAX = -2**63, 2**63 - 1


class CliError(Exception):
    """A failure to report on stderr; the command exits with 1."""


# --- ROS session ---------------------------------------------------------------------------------------
class RosSession:
    """rclpy set up for one command: its own context, a hidden node and an executor; shut down on exit."""

    def __init__(self, ros_args: Sequence[str]) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.parameter import Parameter

        self.context = Context()
        rclpy.init(args=["ipc-component", *ros_args], context=self.context)
        try:
            self.node = Node(
                f"_ipc_component_{os.getpid()}", context=self.context, start_parameter_services=False,
                enable_rosout=False,
                parameter_overrides=[Parameter("start_type_description_service", value=False)])
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
        except BaseException:
            rclpy.try_shutdown(context=self.context)
            raise

    def __enter__(self) -> "RosSession":
        return self

    def __exit__(self, *exc: Any) -> None:
        import rclpy

        try:
            self.executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
        finally:
            rclpy.try_shutdown(context=self.context)

    def find_container(self, container: str, deadline: float) -> None:
        """Wait (until ``deadline``) for ``container`` to show up as a container; CliError if it does not."""
        from ipc_component.container_discovery import list_containers

        found = list_containers(self.node, self.executor, deadline=deadline, discovery_until=deadline,
                                container=container, list_components=False)
        if not found:
            raise CliError(f"Unable to find container node '{container}'")

    def container_client(self, srv_type: Any, container: str, service: str, deadline: float) -> Any:
        """A client of ``<container>/_container/<service>``, found, ready and able to get replies.

        Both clients (this one, then the harmless ListNodes one) are created before anything is waited for,
        so that they are announced in this participant's first discovery exchange with the container
        instead of a second one after it. The order matters: endpoints are announced in creation order over
        one reliable, ordered discovery stream, so once the container answers ListNodes it has also matched
        this client's reply reader.
        """
        from composition_interfaces.srv import ListNodes

        from ipc_component.repeated_call import RepeatedCall

        client = self.node.create_client(srv_type, f"{container}/_container/{service}")
        harmless = RepeatedCall(self.node.create_client(ListNodes, f"{container}/_container/list_nodes"),
                                ListNodes.Request)
        try:
            self.find_container(container, deadline)
            self.ensure_replies(harmless, deadline)
        finally:
            harmless.close()
            self.node.destroy_client(harmless.client)
        while not client.service_is_ready():
            if time.monotonic() >= deadline:
                raise CliError(f"No '{service}' service found for '{container}' container")
            self.executor.spin_once(timeout_sec=0.02)
        return client

    def ensure_replies(self, harmless: Any, deadline: float) -> None:
        """Make sure the container can answer this process before sending a request that must not be lost.

        A service is "ready" once this side has matched it; the container may not have discovered this
        process's reply readers yet, and Fast DDS then drops the reply. A harmless ListNodes call, repeated
        until one is answered (``harmless``, a ipc_component.repeated_call.RepeatedCall), waits out
        that discovery (at most until ``deadline``; then the real call goes ahead and its own timeout applies).
        """
        while harmless.reply is None and time.monotonic() < deadline:
            harmless.step(time.monotonic())
            self.executor.spin_once(timeout_sec=0.02)

    def call(self, client: Any, request: Any, container: str, timeout: float = CALL_TIMEOUT) -> Any:
        """Call a service and wait for the reply, at most ``timeout`` s; CliError text is the reason."""
        future = client.call_async(request)
        deadline = time.monotonic() + timeout
        absent_since: float | None = None
        try:
            while not future.done():
                now = time.monotonic()
                if now >= deadline:
                    raise CliError(f"No reply from '{container}' container within {timeout:g} s")
                self.executor.spin_once(timeout_sec=min(0.1, deadline - now))
                if future.done():
                    break
                if client.service_is_ready():
                    absent_since = None
                elif absent_since is None:
                    absent_since = now
                elif now - absent_since > GONE_GRACE:
                    raise CliError(f"'{container}' container left before replying")
        finally:
            if not future.done():
                future.cancel()
                client.remove_pending_request(future)
        return future.result()


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
    lines = []
    if args.container_node_name is not None:
        if not listings:
            raise CliError(f"Unable to find container node '{args.container_node_name}'")
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
    _print_lines(lines)
    return 0


# --- load -----------------------------------------------------------------------------------------------
def parse_log_level(text: str | None) -> int:
    """The rcl_interfaces/msg/Log level for ``--log-level`` (0: not given)."""
    if text is None:
        return 0
    level = LOG_LEVELS.get(text.strip().upper())
    if level is None and text.strip().isdigit() and int(text) in LOG_LEVELS.values():
        level = int(text)
    if level is None:
        raise CliError(f"Invalid log level '{text}': use {LOG_LEVEL_HELP}")
    return level


def parameter_msgs(arguments: Sequence[str] | None, what: str) -> list[Any]:
    """rcl_interfaces/Parameter messages for ``name:=value`` arguments, values typed as YAML."""
    from component_container.parameter_values import parameter_msg, parse_assignment

    messages = []
    for argument in arguments or ():
        try:
            name, value = parse_assignment(argument)
        except ValueError:
            raise CliError(f"Malformed {what} '{argument}': expected name:=value") from None
        integers = value if isinstance(value, list) else [value]
        if any(isinstance(item, int) and not isinstance(item, bool) and not INT64_MIN <= item <= INT64_MAX
               for item in integers):
            raise CliError(f"Invalid {what} '{argument}': integer out of the 64-bit signed range")
        try:
            messages.append(parameter_msg(name, value))
        except Exception as exc:  # noqa: BLE001 - whatever the message types refuse
            raise CliError(f"Invalid {what} '{argument}': {exc or type(exc).__name__}") from None
    return messages


def remap_rules(arguments: Sequence[str] | None) -> list[str]:
    rules = list(arguments or ())
    for rule in rules:
        source, separator, _ = rule.partition(":=")
        if not separator or not source:
            raise CliError(f"Malformed remap rule '{rule}': expected from:=to")
    return rules


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
        try:
            response = ros.call(client, request, container)
        except CliError as exc:
            raise CliError(f"Failed to load component: {exc}") from None
    if not response.success:
        raise CliError(f"Failed to load component: {_capitalized(response.error_message)}")
    if args.quiet:
        _print_lines([f"{response.unique_id}  {response.full_node_name}"])
    else:
        _print_lines([f"Loaded component {response.unique_id} into '{container}' container node as "
                      f"'{response.full_node_name}'"])
    return 0


# --- unload ---------------------------------------------------------------------------------------------
def parse_unique_id(text: str) -> int:
    try:
        value = int(text, 10)
    except ValueError:
        value = -1
    if not 0 <= value <= UINT64_MAX:
        raise CliError(f"Invalid component unique id '{text}': expected a non-negative integer")
    return value


def run_unload(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    from composition_interfaces.srv import UnloadNode

    container = args.container_node_name
    unique_ids = [parse_unique_id(text) for text in args.component_uid]
    start = time.monotonic()
    with RosSession(ros_args) as ros:
        client = ros.container_client(UnloadNode, container, "unload_node", start + BUDGET)
        for uid in unique_ids:
            try:
                response = ros.call(client, UnloadNode.Request(unique_id=uid), container)
                reason = None if response.success else response.error_message
            except CliError as exc:
                reason = str(exc)
            if reason is not None:
                raise CliError(f"Failed to unload component {uid} from '{container}' container node\n"
                               f"    {_capitalized(reason)}")
            _print_lines([str(uid) if args.quiet else
                          f"Unloaded component {uid} from '{container}' container node"])
    return 0


# --- types ----------------------------------------------------------------------------------------------
def run_types(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    # Only the local installation is consulted: no ROS communication, so no rclpy session is needed.
    from component_container.plugin_registry import PluginRegistry

    plugins = PluginRegistry().plugins_by_package()
    if args.package_name is not None:
        if args.package_name not in plugins:
            raise CliError(f"Unable to find package '{args.package_name}'")
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

    try:
        print(format_bag_info(args.bag_path), flush=True)
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
                                  description="Call `ipc-component <command> -h` for more detailed usage.")
    verbs.required = True

    add: Callable[..., argparse.ArgumentParser] = verbs.add_parser
    p = add("list", help="Output a list of running containers and components",
            description="Output a list of running containers and components.")
    p.add_argument("container_node_name", nargs="?", default=None,
                   help="Name of the container node to list components from")
    p.add_argument("--containers-only", action="store_true", help="List found containers nodes only")
    p.add_argument("--spin-time", type=float, default=LIST_DISCOVERY,
                   help=f"Seconds to watch the graph for containers when no container is named "
                        f"(default {LIST_DISCOVERY:g}; everything stays within a {BUDGET:g} s budget)")
    p.set_defaults(handler=run_list)

    p = add("load", help="Load a component into a container node",
            description="Load a component into a container node.")
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

    p = add("unload", help="Unload a component from a container node",
            description="Unload a component from a container node.")
    p.add_argument("container_node_name", help="Container node name to unload component from")
    p.add_argument("component_uid", nargs="+", help="Unique ID of the component to be unloaded")
    p.add_argument("-q", "--quiet", action="store_true", help="Only print component unique IDs")
    p.set_defaults(handler=run_unload)

    p = add("types", help="Output a list of components registered in this installation",
            description="Output a list of components registered (rclpy_components entry points).")
    p.add_argument("package_name", nargs="?", default=None,
                   help="Package name to look for registered components in")
    p.set_defaults(handler=run_types)

    from ipc_component import create  # the verb lives in its own module (no ROS needed)

    p = add("create", help="Create a new package of rclpy components (like `ros2 pkg create`)",
            description="Create a new package of rclpy components: pyproject.toml with the entry point, "
                        "a package with one component class, README.")
    create.add_arguments(p)
    p.set_defaults(handler=create.run_create)

    from ipc_component import top  # its own modules, like the verbs below

    p = add("top", help="A live view of the containers: components, topic rates, drops, free disk",
            description="A live view of the containers in the domain, from their /diagnostics reports and "
                        "ListNodes, redrawn once a second (q or Ctrl-C quits); one plain-text snapshot with "
                        "--once or when the output is not a terminal.")
    top.add_arguments(p)

    from ipc_component import record_fleet  # fleet recording: its own modules

    record_fleet.add_record_parser(verbs)

    p = add("bag", help="Inspect and play rosbag2 bags (what `ros2 bag` offers)",
            description="Inspect and play rosbag2 bags.")
    bag_verbs = p.add_subparsers(dest="bag_verb", title="commands")
    bag_verbs.required = True
    p = bag_verbs.add_parser("info", help="Print information about a bag (like `ros2 bag info`)",
                             description="Print information about a bag (like `ros2 bag info`).")
    p.add_argument("bag_path", help="Bag directory (with metadata.yaml)")
    p.set_defaults(handler=run_bag_info)
    p = bag_verbs.add_parser(
        "recover", aliases=["reindex"], help="Make a bag a crash left unfinished readable again",
        description="Keep every intact record (MCAP) or committed row (SQLite3) of every file, rebuild "
                    "indexes and summaries, regenerate metadata.yaml, and report what was cut. "
                    "Crash-safe: files are replaced only once their repaired version is on disk.")
    p.add_argument("bag_path", help="Bag directory (metadata.yaml may be missing)")
    p.add_argument("-o", "--output", default=None,
                   help="Write the recovered bag to this new directory instead of in place")
    p.set_defaults(handler=run_bag_recover)
    bag_merge.register(bag_verbs)
    p = bag_verbs.add_parser("play", help="Play back bags (like `ros2 bag play`)",
                             description="Play back bags (several: one timeline) like `ros2 bag play`.")
    bag_play.add_arguments(p)
    p.set_defaults(handler=bag_play.run_bag_play)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(own)
    try:
        return args.handler(args, ros_args)
    except CliError as exc:
        sys.stdout.flush()
        print(exc, file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    # ``python -m ipc_component.cli``: run the package's module, not this ``__main__`` copy of it, so that the
    # CliError raised by the verbs in other modules (which import ipc_component.cli) is the one main() catches.
    from ipc_component import cli

    sys.exit(cli.main())
