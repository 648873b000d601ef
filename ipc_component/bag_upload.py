"""``ipc-component bag upload BAG... s3://BUCKET/PREFIX``: bags to S3-compatible object storage.

Reads and uploads files only (no ROS session); the work is :func:`baglib.upload.bag_upload.upload_bags`. This
module is its command line: the arguments, a progress bar on a terminal (stderr), the summary on stdout, and a
worded error on stderr with exit status 1 (wrong credentials, a missing bucket, an unreachable endpoint, a bag
that is not finished).
"""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ipc_component.ros_session import CliError
from ipc_component.verb_arguments import add_verb


def register(bag_verbs: Any) -> None:
    """Add the ``upload`` verb to ``ipc-component bag``'s sub-parsers."""
    parser = add_verb(bag_verbs, "upload", "Upload bags to S3-compatible object storage, resumable and verified",
                      "Each file is verified against the local bytes (size and ETag); metadata.yaml goes last, so a "
                      "bag is complete in the store exactly when its metadata.yaml is there. Credentials come from "
                      "the AWS environment, ~/.aws or a profile.")
    parser.add_argument("paths", nargs="+", metavar="BAG", help="Bag directories (finalized)")
    parser.add_argument("uri", metavar="s3://BUCKET/PREFIX", help="Where the bags go: PREFIX/<bag>/<file>")
    parser.add_argument("--endpoint-url", default="", help="An S3-compatible store (default: the AWS configuration)")
    parser.add_argument("--delete-after", action="store_true",
                        help="Delete each local file once its remote copy is verified")
    parser.add_argument("--resume", action="store_true",
                        help="Also finish every upload the journals next to the bags hold unfinished (a container "
                             "that exited first, a cut bag upload); BAG may then be a directory of bags")
    parser.add_argument("--max-rate", type=float, default=0.0, metavar="BYTES_PER_S",
                        help="Upload at most this many bytes per second (default: unlimited)")
    parser.set_defaults(handler=run_bag_upload)


class _ProgressBar:
    """One line on a terminal: the file, bytes sent, the rate."""

    def __init__(self) -> None:
        self.started = time.monotonic()
        self.sent = 0

    def __call__(self, entry: Any, sent: int) -> None:
        self.sent += sent
        rate = self.sent / max(1e-3, time.monotonic() - self.started)
        sys.stderr.write(f"\r{entry.local.parent.name}/{entry.local.name}: {self.sent / 1e6:9.1f} MB sent, "
                         f"{rate / 1e6:6.1f} MB/s   ")
        sys.stderr.flush()


def run_bag_upload(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    from baglib.upload.bag_upload import upload_bags
    from baglib.upload.client import UploadError
    from baglib.upload.location import parse_s3_uri

    try:
        location = parse_s3_uri(args.uri, "the destination")
    except ValueError as error:
        raise CliError(str(error)) from None
    if args.max_rate < 0:
        raise CliError("--max-rate must be >= 0 bytes per second")
    bar = _ProgressBar() if sys.stderr.isatty() else None
    try:
        report = upload_bags([Path(path) for path in args.paths], location, args.endpoint_url, args.delete_after,
                             args.resume, args.max_rate, bar or (lambda entry, sent: None),
                             lambda journal: print(f"Another process is uploading from {journal}: waiting for it",
                                                   file=sys.stderr, flush=True))
    except UploadError as error:
        raise CliError(f"bag upload: {error}") from None
    finally:
        if bar is not None:
            sys.stderr.write("\n")
    print(report.text(), flush=True)
    return 0
