"""The bag verbs that read a bag in S3-compatible storage: ``bag download`` and ``bag info s3://...``.

``ipc-component bag download s3://BUCKET/PREFIX/BAG DIR`` fetches a bag complete in the store into ``DIR/BAG``,
resumably and verified (:mod:`baglib.upload.download`). ``bag info s3://BUCKET/PREFIX/BAG`` prints what ``bag
info`` prints of the same bag downloaded, from its ``metadata.yaml`` and one listing of its objects; ``bag info
s3://.../file.mcap`` reads one MCAP object's footer and summary with range requests
(:class:`baglib.upload.remote_read.RangedFile`), not the whole file. Credentials come from the standard AWS chain
(:mod:`baglib.upload.client`); every failure is one worded line on stderr and exit status 1.
"""
from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from ipc_component.ros_session import CliError
from ipc_component.verb_arguments import add_verb

ENDPOINT_HELP = "The S3-compatible store's URL (default: the AWS configuration, e.g. AWS_ENDPOINT_URL)"


def register(bag_verbs: Any) -> None:
    """Add the ``download`` verb to ``ipc-component bag``'s sub-parsers."""
    parser = add_verb(bag_verbs, "download", "Download a bag from S3-compatible storage, resumably and verified",
                      "Only a bag complete in the store (its metadata.yaml there) is taken. Each file is written "
                      "as FILE.part, continued from where an earlier run stopped, verified (size and ETag) and "
                      "then renamed; metadata.yaml last. A file already here that verifies is not fetched again. "
                      "Credentials come from the AWS environment, ~/.aws or a profile.")
    parser.add_argument("uri", help="The bag in the store: s3://BUCKET/PREFIX/BAG")
    parser.add_argument("directory", type=Path, help="Where to put it: the bag becomes DIRECTORY/BAG")
    parser.add_argument("--endpoint-url", default="", help=ENDPOINT_HELP)
    parser.set_defaults(handler=run_bag_download)


def is_remote(bag: str) -> bool:
    """``bag`` names a bag or a file in a store."""
    return bag.startswith("s3://")


@contextlib.contextmanager
def worded_errors(what: str) -> Iterator[None]:
    """Any failure of the store, its client or the bag as one CliError line saying ``what`` failed and why."""
    from baglib.read.storage_reader import BagReadError
    from baglib.upload.client import describe

    try:
        yield
    except (ValueError, BagReadError) as error:
        raise CliError(str(error)) from None
    except Exception as error:  # noqa: BLE001 - the client's errors, worded by describe
        raise CliError(str(describe(error, what))) from None


def run_bag_download(args: argparse.Namespace, ros_args: Sequence[str]) -> int:
    """Download, a line per file and a total; exit status 1 with the reason on a failure."""
    from baglib.upload.client import make_client
    from baglib.upload.download import Downloaded, bag_name, download_bag
    from baglib.upload.location import parse_s3_uri

    def report(done: Downloaded) -> None:
        if done.already_here:
            print(f"{done.name}: already here, verified ({done.size} bytes)", flush=True)
        else:
            resumed = f", resumed after {done.resumed} bytes" if done.resumed else ""
            print(f"{done.name}: {done.fetched} bytes fetched{resumed}, verified", flush=True)

    with worded_errors(f"downloading {args.uri}"):
        location = parse_s3_uri(args.uri, "the bag")
        files = download_bag(make_client(args.endpoint_url), location, args.directory, report)
    fetched = sum(done.fetched for done in files)
    here = sum(done.already_here for done in files)
    print(f"{args.directory / bag_name(location)}: {len(files)} files, {fetched} bytes fetched"
          + (f", {here} already here" if here else ""), flush=True)
    return 0


def remote_info(args: argparse.Namespace) -> str:
    """``bag info`` of an ``s3://`` bag (its ``metadata.yaml``) or MCAP object (its summary, by range)."""
    from baglib.read.reader import BagReader
    from baglib.tools.info import directory_summary, file_summary, format_bag_info
    from baglib.upload.client import make_client
    from baglib.upload.location import parse_s3_uri
    from baglib.upload.remote_read import RangedFile, object_sizes, read_metadata

    if args.verbose:
        raise CliError("bag info --verbose reads every message: download the bag first (ipc-component bag "
                       "download)")
    with worded_errors(f"reading {args.bag_path}"):
        location = parse_s3_uri(args.bag_path, "the bag")
        client = make_client(args.endpoint_url)
        if location.prefix.endswith(".mcap"):
            with RangedFile(client, location.bucket, location.prefix) as source, \
                    BagReader(args.bag_path, source=source) as reader:
                summary = file_summary(reader, source.size)
        else:
            summary = directory_summary(read_metadata(client, location), object_sizes(client, location))
        return format_bag_info(args.bag_path, args.sort, args.verbose, args.topic_name, summary)
