"""``ipc-component bag play BAG [BAG ...]``: what ``ros2 bag play`` does, as a container of one ``components::Player``.

Several bags (positional, or rosbag2 Kilted's ``-i BAG [STORAGE_ID]`` repeated; not both) play as one timeline.

The command runs a container in its own process (no separate container to start) and loads the player by
plugin name, with the command's options as the player's rosbag2 parameters; while it plays, a terminal shows
one progress line (bag position / duration, rate, state), updated in place; a log line clears it and takes its
place, so the two never share a line. The player's services
(``/rosbag2_player/pause``...) work as with ``ros2 bag play``. It exits when playback ends (never with
``--loop``) or on Ctrl-C, which stops playback and unloads the player within the shutdown timeout.
"""
from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, TextIO

from ipc_component.ros_session import end_ros_later
from ipc_component.verb_arguments import in_options

PLAYER_PLUGIN = "components::Player"
PROGRESS_PERIOD = 0.25
#: Back to the start of the terminal line, then erase it (ANSI).
CLEAR_LINE = "\r\033[K"
#: rcutils' console format when RCUTILS_CONSOLE_OUTPUT_FORMAT is not set.
DEFAULT_LOG_FORMAT = "[{severity}] [{time}] [{name}]: {message}"
_NS_PER_S = 1_000_000_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``ros2 bag play`` options this player supports, with its names."""
    parser.add_argument("bag_paths", nargs="*", metavar="bag_path",
                        help="Bag directory, or a single .mcap / .db3 file; several play as one timeline")
    parser.add_argument("-i", "--input", action="append", nargs="+", default=[], metavar=("URI", "STORAGE_ID"),
                        dest="inputs", help="A bag to play, with its storage id (default: detect); repeat it to "
                                            "play several bags as one timeline (instead of positional bags)")
    parser.add_argument("-s", "--storage", default="", choices=("mcap", "sqlite3"),
                        help="Storage identifier of the positional bags (default: detect)")
    parser.add_argument("-r", "--rate", type=float, default=1.0, help="Rate at which to play back messages")
    parser.add_argument("-l", "--loop", action="store_true", help="Enables loop playback")
    parser.add_argument("--topics", nargs="+", default=[], help="Topics to replay, separated by space")
    parser.add_argument("--services", nargs="+", default=[], help="Services to replay, separated by space")
    parser.add_argument("--actions", nargs="+", default=[], help="Actions to replay, separated by space")
    parser.add_argument("-e", "--regex", default="",
                        help="Play only topics, services and actions matching this regex")
    parser.add_argument("-x", "--exclude-regex", default="",
                        help="Exclude topics, services and actions matching this")
    parser.add_argument("--exclude-topics", nargs="+", default=[], help="Topics not to replay")
    parser.add_argument("--exclude-services", nargs="+", default=[], help="Services not to replay")
    parser.add_argument("--exclude-actions", nargs="+", default=[], help="Actions not to replay")
    parser.add_argument("--qos-profile-overrides-path", default="", help="QoS overrides file (YAML)")
    parser.add_argument("--remap", "-m", nargs="+", default=[], help="Remappings, in the 'from:=to' form")
    parser.add_argument("--read-ahead-queue-size", type=int, default=1000,
                        help="Messages to read ahead of playback (default 1000)")
    clock = parser.add_mutually_exclusive_group()
    clock.add_argument("--clock", type=float, nargs="?", const=40.0, default=0.0, metavar="HZ",
                       help="Publish /clock at this frequency (default 40 Hz when given without a value); the "
                            "bag's own /clock topic is then not played")
    clock.add_argument("--clock-topics", nargs="+", default=[], metavar="TOPIC",
                       help="Publish /clock right before each message of these topics")
    clock.add_argument("--clock-topics-all", action="store_true",
                       help="Publish /clock right before each message played")
    parser.add_argument("-d", "--delay", type=float, default=0.0, help="Sleep this many seconds before playing")
    parser.add_argument("--playback-duration", type=float, default=-1.0,
                        help="Seconds of the bag to play (default: all)")
    until = parser.add_mutually_exclusive_group()
    until.add_argument("--playback-until-sec", type=float, default=-1.0,
                       help="Play until this bag timestamp, in seconds since epoch (0 or negative: no limit); "
                            "mutually exclusive with --playback-until-nsec")
    until.add_argument("--playback-until-nsec", type=int, default=-1,
                       help="Play until this bag timestamp, in nanoseconds since epoch, exactly (0 or negative: no "
                            "limit); mutually exclusive with --playback-until-sec")
    parser.add_argument("--start-offset", type=float, default=0.0, help="Start this many seconds into the bag")
    parser.add_argument("-p", "--start-paused", action="store_true", help="Start paused")
    parser.add_argument("--wait-for-all-acked", type=int, default=-1, metavar="TIMEOUT_MS",
                        help="At the end, wait for reliable readers to acknowledge (0: no limit)")
    parser.add_argument("--publish-service-requests", action="store_true",
                        help="Call the recorded services with the recorded requests instead of publishing "
                             "their events")
    parser.add_argument("--send-actions-as-client", action="store_true",
                        help="Send the recorded goals, cancel and result requests to the running action servers "
                             "instead of publishing the actions' topics")
    parser.add_argument("--service-requests-source", default="service_introspection",
                        choices=("service_introspection", "client_introspection"),
                        help="Which side's recorded requests are sent (services and actions)")
    parser.add_argument("--message-order", default="received", choices=("received", "sent"),
                        help="The timestamp messages are ordered and played by: when they were received "
                             "(recorded) or when they were sent (published). With 'sent', messages are "
                             "ordered within the read-ahead queue: raise --read-ahead-queue-size if some are "
                             "still out of order")
    parser.add_argument("--decode", nargs="*", default=None, metavar="TOPIC",
                        help="Also play compressed image topics (sensor_msgs/CompressedImage, "
                             "foxglove_msgs/CompressedVideo) decoded as sensor_msgs/Image on <base> for "
                             "<base>/compressed or <base>/video: all of them, or the topics named (with no bag "
                             "named elsewhere, the last word after it is the bag)")
    parser.add_argument("--no-progress", action="store_true", help="No progress line, even on a terminal")


def duration_parameters(name: str, seconds: float) -> dict[str, int]:
    """rosbag2's .sec/.nsec pair; negative seconds (disabled) stay negative."""
    return _nanoseconds(name, round(seconds * _NS_PER_S))


def _nanoseconds(name: str, nanoseconds: int) -> dict[str, int]:
    """rosbag2's .sec/.nsec pair for a whole number of nanoseconds (no float on the way: an epoch timestamp in
    nanoseconds has more digits than a double holds)."""
    sign = -1 if nanoseconds < 0 else 1
    return {f"{name}.sec": sign * (abs(nanoseconds) // _NS_PER_S), f"{name}.nsec": sign * (abs(nanoseconds) % _NS_PER_S)}


def bags_and_decoded(args: argparse.Namespace) -> tuple[list[str], list[str] | None]:
    """The positional bags, and the topics of ``--decode`` (None: not given).

    ``--decode`` takes topics after it, so argparse hands it every word that follows, the bag too. ``ros2 bag
    play`` takes its bag anywhere, so when no bag is named otherwise, the last of those words is the bag:
    ``bag play --decode BAG`` decodes every topic of BAG, ``bag play --decode TOPIC BAG`` one.
    """
    if args.decode and not args.bag_paths and not args.inputs:
        return args.decode[-1:], args.decode[:-1]
    return args.bag_paths, args.decode


def input_bags(args: argparse.Namespace) -> list[tuple[str, str]]:
    """(path, storage id) of every bag to play; ValueError for a command line that names none, or mixes
    positional bags and ``-i`` (as rosbag2 refuses to)."""
    bag_paths = bags_and_decoded(args)[0]
    if bag_paths and args.inputs:
        raise ValueError("do not mix positional bags and the -i,--input option; for several input bags, name them "
                         "all one way")
    if not bag_paths and not args.inputs:
        raise ValueError("name the bag to play (bag_path, or -i URI)")
    for given in args.inputs:
        if len(given) > 2 or given[1:] not in ([], ["mcap"], ["sqlite3"], [""]):
            raise ValueError(f"-i takes a bag and optionally its storage id (mcap or sqlite3), got {' '.join(given)}")
    return [(path, args.storage) for path in bag_paths] + [(given[0], given[1] if given[1:] else "")
                                                          for given in args.inputs]


#: The player's parameters that the options set, by the option's name: what a load error of the player is told in
#: (the player names its parameters; the user typed options). The bags: their positional name, or -i.
OPTIONS = {"play.rate": "--rate", "play.topics_to_filter": "--topics", "play.services_to_filter": "--services",
           "play.actions_to_filter": "--actions", "play.regex_to_filter": "--regex",
           "play.exclude_regex_to_filter": "--exclude-regex", "play.exclude_topics_to_filter": "--exclude-topics",
           "play.exclude_services_to_filter": "--exclude-services",
           "play.exclude_actions_to_filter": "--exclude-actions",
           "play.qos_profile_overrides_path": "--qos-profile-overrides-path",
           "play.read_ahead_queue_size": "--read-ahead-queue-size", "play.clock_publish_frequency": "--clock",
           "play.clock_trigger_topics": "--clock-topics", "play.service_requests_source": "--service-requests-source",
           "play.message_order": "--message-order", "play.decode": "--decode", "play.decode_topics": "--decode"}


def options_of(bags: str, storage: str) -> dict[str, str]:
    """:data:`OPTIONS` with the bag parameters: ``bags`` names the bags as given (``bag_path``, ``-i``),
    ``storage`` their storage ids (``--storage``, ``-i``)."""
    return {**OPTIONS, "storage.uri": bags, "storage.uris": bags, "storage.storage_id": storage,
            "storage.storage_ids": storage}


def _storage_parameters(bags: list[tuple[str, str]]) -> dict[str, Any]:
    if len(bags) == 1:
        return {"storage.uri": bags[0][0], "storage.storage_id": bags[0][1]}
    return {"storage.uris": [path for path, _ in bags], "storage.storage_ids": [storage for _, storage in bags]}


def player_parameters(args: argparse.Namespace) -> dict[str, Any]:
    """The player's parameters for the command's options (ValueError: see :func:`input_bags`)."""
    decode = bags_and_decoded(args)[1]
    parameters: dict[str, Any] = {
        **_storage_parameters(input_bags(args)),
        "play.rate": args.rate,
        "play.loop": args.loop,
        "play.topics_to_filter": args.topics or [""],
        "play.services_to_filter": args.services or [""],
        "play.regex_to_filter": args.regex,
        "play.exclude_regex_to_filter": args.exclude_regex,
        # as ros2bag: a player publishing /clock does not also play the bag's /clock
        "play.exclude_topics_to_filter": args.exclude_topics + (["/clock"] if args.clock > 0 else []) or [""],
        "play.exclude_services_to_filter": args.exclude_services or [""],
        "play.qos_profile_overrides_path": args.qos_profile_overrides_path,
        "play.read_ahead_queue_size": args.read_ahead_queue_size,
        "play.clock_publish_frequency": args.clock,
        "play.clock_publish_on_topic_publish": args.clock_topics_all or bool(args.clock_topics),
        "play.clock_trigger_topics": args.clock_topics or [""],
        "play.start_paused": args.start_paused,
        "play.publish_service_request": args.publish_service_requests,
        "play.service_requests_source": args.service_requests_source.upper(),
        "play.message_order": f"{args.message_order.upper()}_TIMESTAMP",
        "play.actions_to_filter": args.actions or [""],
        "play.exclude_actions_to_filter": args.exclude_actions or [""],
        "play.send_actions_as_client": args.send_actions_as_client,
        "play.decode": decode is not None,
        "play.decode_topics": decode or [""],
        **duration_parameters("play.delay", args.delay),
        **duration_parameters("play.playback_duration", args.playback_duration),
        **duration_parameters("play.start_offset", args.start_offset),
        **duration_parameters("play.wait_acked_timeout",
                              args.wait_for_all_acked / 1000 if args.wait_for_all_acked >= 0 else -1.0),
    }
    until_ns = playback_until_ns(args.playback_until_sec, args.playback_until_nsec)
    if until_ns >= 0:
        parameters.update(_nanoseconds("play.playback_until_timestamp", until_ns))
    return parameters


def playback_until_ns(seconds: float, nanoseconds: int) -> int:
    """The "until" timestamp of ``--playback-until-sec`` / ``--playback-until-nsec``, -1 for none.

    As ros2bag's ``get_playback_until_from_arg_group``: a positive value of either sets it, and 0 is no limit,
    like a negative one (the player's own parameter, ``play.playback_until_timestamp``, reads 0 as "publish
    nothing"; the command line never asks for that).
    """
    if seconds > 0:
        return round(seconds * _NS_PER_S)
    return nanoseconds if nanoseconds > 0 else -1


def container_name(bag_path: str) -> str:
    """``bag_play_<bag name>``, with what a node name cannot hold replaced by ``_``."""
    return "bag_play_" + re.sub(r"[^A-Za-z0-9_]", "_", bag_path.rstrip("/").rsplit("/", 1)[-1])


def progress_line(stats: dict[str, Any]) -> str:
    """``[PLAYING]  12.345 / 60.000 s  rate 1.00  1234 msgs``, as the player's stats say."""
    state = "PAUSED" if stats["paused"] else ("PLAYING" if stats["playing"] else "FINISHED")
    published = sum(stats["published"].values())
    return (f"[{state}]  {stats['position_ns'] / _NS_PER_S:.3f} / {stats['duration_ns'] / _NS_PER_S:.3f} s  "
            f"rate {stats['rate']:.2f}  {published} msgs")


def logs_clear_the_progress_line() -> None:
    """Make every log line of this process start by clearing the terminal line it is written on.

    The progress line is redrawn in place and never ended while playing; a log line (the player's warnings, on
    stderr, the same terminal) would be appended to it. With the clearing prefix a log line replaces the progress
    line and ends it, and the next progress update draws on the line below. rcutils reads its console format
    once, when rclpy first configures logging, so this runs before ``rclpy.init``; a format of the user's own is
    kept behind the prefix.
    """
    line_format = os.environ.get("RCUTILS_CONSOLE_OUTPUT_FORMAT") or DEFAULT_LOG_FORMAT
    if not line_format.startswith(CLEAR_LINE):
        os.environ["RCUTILS_CONSOLE_OUTPUT_FORMAT"] = CLEAR_LINE + line_format


def run_bag_play(args: argparse.Namespace, ros_args: Sequence[str], out: TextIO = sys.stdout) -> int:
    """Play a bag in this process; returns the exit status."""
    try:
        parameters = player_parameters(args)
    except ValueError as exc:
        print(f"ipc-component bag play: {exc}", file=sys.stderr, flush=True)
        return 1
    return run_player(parameters, [path for path, _ in input_bags(args)], args.remap, args.no_progress, ros_args,
                      out, options=options_of("-i", "-i") if args.inputs else options_of("bag_path", "--storage"))


def run_player(parameters: dict[str, Any], bags: list[str], remap: list[str], no_progress: bool,
               ros_args: Sequence[str], out: TextIO = sys.stdout,
               when_loaded: Callable[[Any], None] | None = None, options: dict[str, str] | None = None) -> int:
    """Run a container with one player of ``parameters`` in this process until its playback ends (or Ctrl-C);
    ``when_loaded`` gets the player once it is loaded (on a thread of its own, so Ctrl-C still stops it). A load
    error names each parameter in ``options`` (parameter -> option) as the option that set it."""
    import rclpy
    from rclpy.context import Context

    from component_container.component_manager import ComponentConstructionError, ComponentManager
    from component_container.discovery_profile import use_fastdds_profile
    from component_container.process_tuning import apply_low_latency
    from component_container.startup_file import load_request
    from component_container.supervisor import ExitRequest

    show = out.isatty() and not no_progress
    if show and sys.stderr.isatty():
        logs_clear_the_progress_line()
    stop = ExitRequest()  # polled: a signal handled while waiting on a threading.Event can block for good
    previous = {sig: signal.signal(sig, lambda signum, _: stop.request(0, signal.Signals(signum).name))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    apply_low_latency()  # this process is a player's own container: tune it for replay timing
    use_fastdds_profile()
    context = Context()
    rclpy.init(args=["ipc-component", *ros_args], context=context)
    manager = None
    try:
        manager = ComponentManager("single", node_name=container_name(bags[0]), context=context)
        request = load_request({"package": "components", "plugin": PLAYER_PLUGIN,
                                "parameters": parameters,
                                "remaps": remap}, 1, "bag play")
        try:
            player = manager.load(request).node
        except Exception as exc:  # noqa: BLE001 - the player's own message names what is wrong
            reason = exc.reason if isinstance(exc, ComponentConstructionError) else str(exc)  # no container words
            print(f"Cannot play {', '.join(bags)}: {in_options(reason, options or {})}", file=sys.stderr, flush=True)
            return 1
        if when_loaded is not None:
            threading.Thread(target=when_loaded, args=(player,), name="bag-play-when-loaded", daemon=True).start()
        while True:
            time.sleep(PROGRESS_PERIOD)
            if stop.requested:
                break
            stats = player.stats()
            if show:
                out.write("\r" + progress_line(stats) + "\033[K")
                out.flush()
            if not stats["playing"] and not stats["paused"]:
                break
        stats = player.stats()
        out.write(("\r" if show else "") + progress_line(stats) + ("\033[K" if show else "") + "\n")
        out.flush()
        return 1 if stats["read_error"] else 0
    finally:
        if manager is not None:
            manager.shutdown()
        end_ros_later(manager, context)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
