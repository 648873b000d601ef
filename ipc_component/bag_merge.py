"""``ipc-component bag merge OUT BAG ...``: the bags of a fleet recording (or any bags) as one bag.

Reads files only (no ROS session). The merge itself is :func:`baglib.tools.merge.merge_bags`; this module is
its command line: the arguments, the summary line on stdout, a refusal on stderr with exit code 1.
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

from ipc_component.verb_arguments import add_verb


def register(bag_verbs: Any) -> None:
    """Add the ``merge`` verb to ``ipc-component bag``'s sub-parsers."""
    parser = add_verb(bag_verbs, "merge", "Merge several bags into one, every message in log-time order",
                      "For example the per-container bags of a fleet recording; streamed.")
    add_arguments(parser)
    parser.set_defaults(handler=run_bag_merge)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("output", help="The bag directory to create (must not exist)")
    parser.add_argument("bags", nargs="+", help="The bags to merge: directories, or single .mcap / .db3 files")
    parser.add_argument("-s", "--storage", default="mcap", choices=("mcap", "sqlite3"),
                        help="Storage of the merged bag (default: mcap)")
    parser.add_argument("--align-clocks", action="store_true",
                        help="Move each bag's times onto the commanding host's clock by its recorded "
                             "ipc.clock_offset_ns (a bag without one is refused)")
    parser.add_argument("--prefix-host", action="store_true",
                        help="Keep each bag's topics apart under /<host> (its ipc.host, else its directory name) "
                             "instead of merging topics of the same name and type")
    parser.add_argument("--prefix-container", action="store_true",
                        help="Keep each bag's topics apart under the full name of the container that recorded it "
                             "(its ipc.container, e.g. /front/container; else its directory name): two rigs on one "
                             "computer. With --prefix-host: /<host>/<container>")
    parser.add_argument("--interleave", action="append", default=[], metavar="TOPIC",
                        help="A topic (name or fnmatch pattern; repeatable) that bags of different containers may "
                             "feed as one, e.g. /tf. Any other topic of the same name from different containers "
                             "is refused unless a prefix keeps them apart")


def run_bag_merge(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    """Merge, print what was written; exit status 1 (and nothing written) on a refusal."""
    from baglib.tools.merge import MergeError, merge_bags

    try:
        report = merge_bags(args.output, args.bags, args.storage, args.align_clocks, args.prefix_host,
                            args.prefix_container, args.interleave)
    except MergeError as error:
        sys.stdout.flush()
        print(error, file=sys.stderr, flush=True)
        return 1
    print(report.text(), flush=True)
    return 0
