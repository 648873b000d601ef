"""A multipart upload verifies against the ETag each store gives a completed object, on two implementations:
nanio's S3 form (the MD5 of the parts' MD5s, ``-N``) and localbucket's MD5 of the whole content, which the
uploader computes only for such an ETag (baglib/upload/digests.py). The same holds when the file is found in the
store already: uploading it again from a fresh journal transfers nothing."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from baglib.upload.digests import PART_SIZE
from baglib.upload.journal import UploadJournal
from baglib.upload.transfer import Transferred
from baglib.upload.uploader import Uploader
from ipc_testing.s3_server import S3Server

BUCKET = "verify"


def upload(server: S3Server, journal_path: Path, path: Path) -> list[Transferred]:
    """Upload ``path`` to ``BUCKET/file.bin`` with a journal at ``journal_path``; what each verified file took."""
    journal = UploadJournal(journal_path)
    done: list[Transferred] = []
    try:
        journal.enqueue(path, f"s3://{BUCKET}", server.endpoint_url, BUCKET, "file.bin", False)
        assert Uploader(journal, on_file=lambda entry, transferred: done.append(transferred)).drain() is None
        assert journal.summary(f"s3://{BUCKET}")["verify_mismatches"] == 0
    finally:
        journal.close()
    return done


@pytest.mark.parametrize("kind, multipart_etag", [("nanio", True), ("localbucket", False)])
def test_a_multipart_upload_verifies_against_either_etag_form(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                               kind: str, multipart_etag: bool) -> None:
    path = tmp_path / "file.bin"
    path.write_bytes(os.urandom(2 * PART_SIZE + 12345))
    with S3Server(tmp_path / "store", kind=kind) as server:
        for name, value in server.env().items():
            monkeypatch.setenv(name, value)
        server.client().create_bucket(Bucket=BUCKET)
        first = upload(server, tmp_path / "first.sqlite3", path)
        assert first[0].sent == path.stat().st_size and not first[0].already_there
        assert server.client().head_object(Bucket=BUCKET, Key="file.bin")["ETag"].endswith('-3"') == multipart_etag
        again = upload(server, tmp_path / "again.sqlite3", path)
        assert again[0].already_there and again[0].sent == 0
