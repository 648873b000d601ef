"""``ipc-component bag export BAG TOPIC OUT``: a recorded compressed image topic as an MP4 file or numbered pictures.

Reads files only (no ROS session). The export itself is :func:`components.image_encoder.export.export_topic` (it
needs the codec libraries, which baglib does not); this module is its command line: the arguments, the summary
line on stdout, a refusal on stderr with exit code 1.
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

from ipc_component.verb_arguments import add_verb


def register(bag_verbs: Any) -> None:
    """Add the ``export`` verb to ``ipc-component bag``'s sub-parsers."""
    parser = add_verb(bag_verbs, "export", "Write a compressed image topic out as an MP4 file or numbered pictures",
                      "CompressedVideo (H.264, H.265, AV1) is remuxed into MP4 without re-encoding; "
                      "CompressedImage goes to OUT/000001.jpg ... (.png for PNG), the recorded bytes as they are.")
    parser.add_argument("bag_path", help="Bag directory, or a single .mcap / .db3 file")
    parser.add_argument("topic", help="A foxglove_msgs/CompressedVideo or sensor_msgs/CompressedImage topic")
    parser.add_argument("output", help="The MP4 file to create (video), or a new or empty directory (stills)")
    parser.set_defaults(handler=run_bag_export)


def run_bag_export(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    """Export, print what was written; exit status 1 on a refusal."""
    from components.image_encoder.export import ExportError, export_topic

    try:
        report = export_topic(args.bag_path, args.topic, args.output)
    except ExportError as error:
        sys.stdout.flush()
        print(f"ipc-component bag export: {error}", file=sys.stderr, flush=True)
        return 1
    print(report.text(), flush=True)
    return 0
