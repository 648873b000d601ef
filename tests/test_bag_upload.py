"""``ipc-component bag upload`` as users run it, against real S3 server processes on loopback: nanio, and
localbucket as a second implementation (it gives a multipart object the whole content's MD5 as ETag, where nanio
and AWS give the MD5 of the parts' MD5s): the bag arrives byte-identical and verified, uploading it again
transfers nothing, with or without the journal; wrong credentials, a missing bucket, an unreachable endpoint and
bad arguments exit non-zero with a message saying so, and leave the local bag as it was."""
from __future__ import annotations

import hashlib
from collections.abc import Iterator
from pathlib import Path

import pytest

from baglib.upload.journal import JOURNAL_NAME
from ipc_testing.s3_server import S3Server
from test_bag_download import BUCKET, MiB, cli, server, write_bag  # noqa: F401 - fixture


def digest_tree(bag: Path) -> dict[str, str]:
    return {path.name: hashlib.sha256(path.read_bytes()).hexdigest() for path in sorted(bag.iterdir())}


def remote_tree(server: S3Server, prefix: str) -> dict[str, str]:
    client = server.client()
    keys = [item["Key"] for item in client.list_objects_v2(Bucket=BUCKET, Prefix=prefix).get("Contents", [])]
    return {key[len(prefix):]: hashlib.sha256(client.get_object(Bucket=BUCKET, Key=key)["Body"].read()).hexdigest()
            for key in keys}


@pytest.fixture
def localbucket(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[S3Server]:
    with S3Server(tmp_path / "localbucket", kind="localbucket") as running:
        for name, value in running.env().items():
            monkeypatch.setenv(name, value)
        running.client().create_bucket(Bucket=BUCKET)
        yield running


@pytest.mark.parametrize("store", ["server", "localbucket"])
def test_an_uploaded_bag_is_byte_identical_and_uploading_it_again_transfers_nothing(
        tmp_path: Path, store: str, request: pytest.FixtureRequest) -> None:
    running: S3Server = request.getfixturevalue(store)
    bag = write_bag(tmp_path / "robot" / "run", 10 * MiB, max_bagfile_size=9 * MiB)  # a multipart file and more
    local = digest_tree(bag)
    uri = f"s3://{BUCKET}/fleet"
    first = cli("bag", "upload", str(bag), uri, "--endpoint-url", running.endpoint_url)
    assert first.returncode == 0, first.stderr
    assert f"Uploaded {len(local)} files" in first.stdout, first.stdout
    assert remote_tree(running, "fleet/run/") == local
    assert max(path.stat().st_size for path in bag.iterdir()) > 8 * MiB  # a multipart upload was verified
    for journal in (True, False):  # the journal says so; without it, the store's ETags do
        if not journal:
            (bag.parent / JOURNAL_NAME).unlink()
        again = cli("bag", "upload", str(bag), uri, "--endpoint-url", running.endpoint_url)
        assert again.returncode == 0, again.stderr
        assert "Uploaded 0 files: 0 bytes sent" in again.stdout, again.stdout
        if not journal:
            assert f"{len(local)} files already in the store, verified: nothing transferred" in again.stdout
    assert digest_tree(bag) == local


@pytest.mark.parametrize("fault, message", [
    ("credentials", "refused the credentials"),
    ("bucket", "the bucket does not exist"),
    ("endpoint", "cannot be reached"),
])
def test_store_faults_exit_non_zero_and_leave_the_bag_as_it_was(
        tmp_path: Path, server: S3Server, monkeypatch: pytest.MonkeyPatch, fault: str, message: str) -> None:
    bag = write_bag(tmp_path / "robot" / "run", 2 * MiB, max_bagfile_size=MiB)
    before = digest_tree(bag)
    endpoint, uri = server.endpoint_url, f"s3://{BUCKET}/fleet"
    if fault == "credentials":
        monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "not-the-secret")
    elif fault == "bucket":
        uri = "s3://no-such-bucket/fleet"
    else:
        endpoint = S3Server(tmp_path / "nobody").endpoint_url  # a free port nobody listens on
    done = cli("bag", "upload", "--delete-after", str(bag), uri, "--endpoint-url", endpoint)
    assert done.returncode == 1 and message in done.stderr, (done.returncode, done.stdout, done.stderr)
    assert "not-the-secret" not in done.stderr and "Traceback" not in done.stderr
    assert digest_tree(bag) == before and not (bag.parent / JOURNAL_NAME).exists()


@pytest.mark.parametrize("arguments, message", [
    (["s3://bags/fleet", "--max-rate", "-1"], "--max-rate must be >= 0"),
    (["/mnt/bags"], "is not an s3:// URI"),
    (["s3://key:secret@bags/fleet"], "must not carry credentials"),
])
def test_bad_arguments_are_refused_before_anything_is_sent(
        tmp_path: Path, server: S3Server, arguments: list[str], message: str) -> None:
    bag = write_bag(tmp_path / "run", MiB)
    done = cli("bag", "upload", str(bag), *arguments, "--endpoint-url", server.endpoint_url)
    assert done.returncode == 1 and message in done.stderr, done.stderr
    assert "secret" not in done.stderr.replace("must not carry credentials", "")
    assert not [line for line in server.requests() if f"PUT /{BUCKET}/" in line]  # no object written


def test_an_unfinished_bag_is_refused_with_the_repair_command(tmp_path: Path, server: S3Server) -> None:
    bag = write_bag(tmp_path / "run", MiB)
    (bag / "metadata.yaml").unlink()
    (bag / "run_1.mcap").write_bytes(b"\x89MCAP0\r\n")  # a file a crash left: no footer
    done = cli("bag", "upload", str(bag), f"s3://{BUCKET}/fleet", "--endpoint-url", server.endpoint_url)
    assert done.returncode == 1 and "metadata.yaml" in done.stderr, done.stderr
