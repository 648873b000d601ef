"""``ipc-component bag burst BAG``: what ``ros2 bag burst`` does, with the ``bag play`` machinery.

``ros2 bag burst`` (ros2bag's ``verb/burst.py``) is a player started paused whose ``burst(num_messages)`` is called
at once: the next ``-n`` messages (0: the whole bag) go out as fast as they can, their timing ignored, then it stays
paused until Ctrl-C, even at the end of the bag (rosbag2's player does not end a run while paused, so that a seek
can follow). Here that is :func:`bag_play.run_player` with
the player's own :meth:`components.player.player.Player.burst`, the method its ``~/burst`` service calls; the
options are ros2bag burst's (no regexes, no excludes, rate 1).
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any, TextIO

from ipc_component.bag_play import duration_parameters, options_of, run_player


def _not_negative(kind: type) -> Any:
    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid {kind.__name__} value: '{text}'") from None
        if value < 0:
            raise argparse.ArgumentTypeError(f"must not be negative, got {text}")
        return value
    return parse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """ros2bag burst's options, with its names."""
    parser.add_argument("bag_path", help="Bag directory, or a single .mcap / .db3 file")
    parser.add_argument("-s", "--storage", default="", choices=("mcap", "sqlite3"),
                        help="Storage identifier of the bag (default: detect)")
    parser.add_argument("-n", "--num-messages", type=_not_negative(int), default=0,
                        help="Burst this many messages, then pause (default 0: the whole bag)")
    parser.add_argument("--topics", nargs="+", default=[], help="Topics to burst (default: all)")
    parser.add_argument("--services", nargs="+", default=[], help="Services to burst (default: all)")
    parser.add_argument("--actions", nargs="+", default=[], help="Actions to burst (default: all)")
    parser.add_argument("--start-offset", type=_not_negative(float), default=0.0,
                        help="Start this many seconds into the bag")
    parser.add_argument("--read-ahead-queue-size", type=int, default=1000,
                        help="Messages to read ahead (default 1000)")
    parser.add_argument("--qos-profile-overrides-path", default="", help="QoS overrides file (YAML)")
    parser.add_argument("--remap", "-m", nargs="+", default=[], help="Remappings, in the 'from:=to' form")
    parser.add_argument("--no-progress", action="store_true", help="No progress line, even on a terminal")


def burst_parameters(args: argparse.Namespace) -> dict[str, Any]:
    """The player's parameters for the command's options: started paused, at rate 1, as ros2bag burst sets them."""
    return {
        "storage.uri": args.bag_path,
        "storage.storage_id": args.storage,
        "play.start_paused": True,
        "play.topics_to_filter": args.topics or [""],
        "play.services_to_filter": args.services or [""],
        "play.actions_to_filter": args.actions or [""],
        "play.read_ahead_queue_size": args.read_ahead_queue_size,
        "play.qos_profile_overrides_path": args.qos_profile_overrides_path,
        **duration_parameters("play.start_offset", args.start_offset),
    }


def run_bag_burst(args: argparse.Namespace, ros_args: Sequence[str], out: TextIO = sys.stdout) -> int:
    """Burst a bag in this process; returns the exit status."""
    return run_player(burst_parameters(args), [args.bag_path], args.remap, args.no_progress, ros_args, out,
                      when_loaded=lambda player: player.burst(args.num_messages),
                      options=options_of("bag_path", "--storage"))
