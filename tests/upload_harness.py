"""What the upload tests share: a real nanio server whose credentials the code under test finds in the standard
AWS environment, a bucket per test, the bucket's content and the journal's state."""
from __future__ import annotations

import hashlib
import itertools
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from botocore.exceptions import ResponseStreamingError
from diagnostic_msgs.msg import DiagnosticStatus

from baglib.upload.journal import JOURNAL_NAME, UploadJournal
from component_container.component_manager import ComponentManager
from ipc_testing.s3_server import S3Server

_buckets = itertools.count()


@pytest.fixture(scope="module")
def s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    """One nanio server for the module; its credentials in this process's environment (and so in every process
    it starts) for the module's duration."""
    saved = dict(os.environ)
    with S3Server(tmp_path_factory.mktemp("s3") / "data") as server:
        os.environ.update(server.env())
        try:
            yield server
        finally:
            os.environ.clear()
            os.environ.update(saved)


@pytest.fixture()
def bucket(s3: S3Server) -> str:
    name = f"bags-{os.getpid()}-{next(_buckets)}"
    s3.client().create_bucket(Bucket=name)
    return name


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def stored(server: S3Server, bucket: str, prefix: str = "") -> dict[str, bytes]:
    """Every object under ``prefix``: key -> content. A key gone between the listing and the read is left out:
    nanio lists the temporary file of a PUT in progress (``.tmp.<id>``) until it renames it, and a read that began
    before the rename ends short (botocore's ResponseStreamingError). A real object read short is then missing
    from the result, which every caller compares with what it expects."""
    client = server.client()
    keys = [item["Key"] for page in client.get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix)
            for item in page.get("Contents", [])]
    objects: dict[str, bytes] = {}
    for key in keys:
        try:
            objects[key] = client.get_object(Bucket=bucket, Key=key)["Body"].read()
        except (client.exceptions.NoSuchKey, ResponseStreamingError):
            continue
    return objects


def download(server: S3Server, bucket: str, prefix: str, directory: Path) -> Path:
    """The objects under ``prefix``/ written into ``directory`` (the test's own copy, with boto3)."""
    for key, data in stored(server, bucket, prefix + "/").items():
        path = directory / key[len(prefix) + 1:]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    return directory


def upload_summary(bag_root: Path, uri: str) -> dict[str, Any]:
    journal = UploadJournal(bag_root / JOURNAL_NAME)
    try:
        return journal.summary(uri)
    finally:
        journal.close()


def unloaded_work(manager: ComponentManager) -> list[DiagnosticStatus]:
    """What the container's /diagnostics list of its unloaded components' work going on (their uploads, their bags
    not finalized)."""
    return [status for status in manager._diagnostic_statuses() if "(unloaded" in status.name]
