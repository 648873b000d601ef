"""One upload of a bag in a process of its own, measured from inside: benchmarks/upload_bench.py's client.

    python benchmarks/upload_client.py boto3|ours BAG s3://BUCKET/PREFIX ENDPOINT_URL

* ``boto3``: boto3's own ``upload_file`` (s3transfer at its default TransferConfig: 8 MiB parts, 10 threads)
  with a client at boto3's defaults (path-style addressing, which a local server needs), file by file in the
  bag's order, ``metadata.yaml`` last, to the keys this project gives them (``PREFIX/<bag>/<file>``);
* ``ours``: this project's ``upload_bags`` (what ``ipc-component bag upload`` runs: the journal, the uploader
  of the recorder's upload process, Content-MD5 per part, each file verified).

Credentials come from the environment (the server's AWS variables). It prints one JSON line: the seconds the
upload took and the CPU seconds this process spent on it (every thread; ``getrusage``), both without the
interpreter's start and the imports, which differ between the two clients and are not the upload.
"""
from __future__ import annotations

import json
import resource
import sys
import time
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):
    sys.path.insert(1, str(REPO))


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def boto3_upload(bag: Path, uri: str, endpoint_url: str) -> Callable[[], None]:
    import boto3
    from botocore.config import Config

    from baglib.upload.bag_upload import bag_files
    from baglib.upload.location import parse_s3_uri
    location = parse_s3_uri(uri).child(bag.name)
    client = boto3.client("s3", endpoint_url=endpoint_url, config=Config(s3={"addressing_style": "path"}))
    files = bag_files(bag)

    def upload() -> None:
        for path in files:
            client.upload_file(str(path), location.bucket, location.key(path.name))
    return upload


def our_upload(bag: Path, uri: str, endpoint_url: str) -> Callable[[], None]:
    from baglib.upload.bag_upload import upload_bags
    from baglib.upload.location import parse_s3_uri
    location = parse_s3_uri(uri)

    def upload() -> None:
        report = upload_bags([bag], location, endpoint_url)
        if report.already_there:
            raise RuntimeError(f"already in the store, nothing measured: {report.already_there}")
    return upload


CLIENTS = {"boto3": boto3_upload, "ours": our_upload}


def main(argv: list[str]) -> int:
    client, bag, uri, endpoint_url = argv
    upload = CLIENTS[client](Path(bag), uri, endpoint_url)
    cpu, started = cpu_seconds(), time.monotonic()
    upload()
    print(json.dumps({"seconds": time.monotonic() - started, "cpu_s": cpu_seconds() - cpu}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
