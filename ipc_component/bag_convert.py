"""``ipc-component bag convert``: ``ros2 bag convert`` (rosbag2 Lyrical), bags rewritten with new storage,
splitting, topics and time windows.

Reads files only (no ROS session). The conversion is :func:`baglib.tools.convert.convert_bags`, its option files
:mod:`baglib.tools.convert_options`; this module is the command line: ``-i URI [STORAGE_ID]`` (repeatable) or
``--input-options`` (not both, as in rosbag2 #2325), ``-o`` the output options, the summary line on stdout, the
warnings and a refusal on stderr (a refusal with exit code 1).
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

from ipc_component.verb_arguments import add_verb


def register(bag_verbs: Any) -> None:
    """Add the ``convert`` verb to ``ipc-component bag``'s sub-parsers."""
    parser = add_verb(bag_verbs, "convert", "Rewrite bags with new storage, splits, topics or a time window",
                      "As ros2 bag convert: the inputs merged by log time, each output bag described in the "
                      "output options YAML (output_bags: uri, storage_id, max_bagfile_size, topics, regex, "
                      "start_time_ns, ...); streamed, and a time window reads only the MCAP chunks it needs.")
    parser.add_argument("-i", "--input", action="append", nargs="+", metavar=("URI", "STORAGE_ID"), default=[],
                        help="An input bag (directory or single .mcap / .db3 file) and optionally its storage id; "
                             "repeatable")
    parser.add_argument("--input-options", metavar="INPUT.yaml",
                        help="YAML with the top-level key input_bags: a list of uri, storage_id, start_time_ns, "
                             "end_time_ns (instead of -i)")
    parser.add_argument("-o", "--output-options", required=True, metavar="OUTPUT.yaml",
                        help="YAML with the top-level key output_bags: a list of rosbag2 StorageOptions and "
                             "RecordOptions, one per output bag")
    parser.set_defaults(handler=run_bag_convert)


def run_bag_convert(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    """Convert, print what was written; exit status 1 (and no output left) on a refusal."""
    from baglib.tools.convert import ConvertError, convert_bags
    from baglib.tools.convert_options import (
        ConvertOptionsError,
        InputBag,
        load_input_options,
        load_output_options,
    )

    try:
        if bool(args.input) == bool(args.input_options):
            raise ConvertOptionsError("give the input bags either with -i/--input or with --input-options "
                                      "(one of them, not both)")
        if any(len(values) > 2 for values in args.input):
            raise ConvertOptionsError("-i/--input takes a URI and optionally a storage id, no more")
        inputs = load_input_options(args.input_options) if args.input_options else \
            [InputBag(*values) for values in args.input]
        report = convert_bags(inputs, load_output_options(args.output_options))
    except (ConvertError, ConvertOptionsError) as error:
        sys.stdout.flush()
        print(f"ipc-component bag convert: {error}", file=sys.stderr, flush=True)
        return 1
    for warning in report.warnings:
        print(f"ipc-component bag convert: warning: {warning}", file=sys.stderr, flush=True)
    print(report.text(), flush=True)
    return 0
