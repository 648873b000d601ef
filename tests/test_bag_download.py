"""``bag download`` and ``bag info s3://...`` against a real S3 server process (nanio on loopback).

Each bag is written with this project's BagWriter and uploaded with the recorder's own upload path (the journal
and the Uploader, ``metadata.yaml`` last); the commands run as users run them, the installed ``ipc-component``
with the server's AWS environment. What is checked: the files downloaded are byte-identical (sha256); a download
cut short (a partial file left, or the server killed mid-way and started again) continues from where it stopped;
a file that does not verify is an error naming it and is never kept; a bag without ``metadata.yaml`` in the store
is refused; wrong credentials, a missing bucket and an unreachable endpoint are worded errors with exit status 1;
``bag info`` of the bag in the store prints what it prints here, and of one MCAP object reads its summary by
range, far less than the file.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from baglib.format.metadata import METADATA_FILENAME
from baglib.upload.journal import JOURNAL_NAME, UploadJournal
from baglib.upload.location import parse_s3_uri
from baglib.upload.uploader import Uploader
from ipc_testing.s3_server import S3Server

IPC_COMPONENT = shutil.which("ipc-component", path=str(Path(sys.executable).parent)) or "ipc-component"
BUCKET = "bags"
PREFIX_URI = f"s3://{BUCKET}/fleet"
T0 = 1_700_000_000_000_000_000
MiB = 1 << 20


def cli(*args: str) -> subprocess.CompletedProcess:
    """``ipc-component args`` with this process's environment (the server's AWS variables)."""
    return subprocess.run([IPC_COMPONENT, *args], capture_output=True, text=True, timeout=60, env=dict(os.environ))


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write_bag(path: Path, payload_bytes: int, max_bagfile_size: int = 0) -> Path:
    """A real MCAP bag of two topics whose messages carry ``payload_bytes`` of random text in all (incompressible
    enough that the files are about that size)."""
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Int32, String

    from baglib.format.metadata import TopicInfo
    from baglib.write.writer import BagWriter

    with BagWriter(path, max_bagfile_size=max_bagfile_size) as writer:
        writer.add_topic(TopicInfo("/blob", "std_msgs/msg/String"))
        writer.add_topic(TopicInfo("/count", "std_msgs/msg/Int32"))
        for n in range(payload_bytes // (64 * 1024)):
            writer.write("/blob", serialize_message(String(data=os.urandom(32 * 1024).hex())), T0 + n * 10**7,
                         T0 + n * 10**7)
            writer.write("/count", serialize_message(Int32(data=n)), T0 + n * 10**7 + 1, T0 + n * 10**7 + 1)
    return path


def upload(server: S3Server, bag: Path, with_metadata: bool = True) -> str:
    """Upload ``bag`` under PREFIX_URI with the recorder's upload path (each file, then ``metadata.yaml``);
    returns the bag's URI."""
    location = parse_s3_uri(PREFIX_URI).child(bag.name)
    journal = UploadJournal(bag.parent / JOURNAL_NAME)
    try:
        files = sorted(path for path in bag.iterdir() if path.name != METADATA_FILENAME)
        for path in files + ([bag / METADATA_FILENAME] if with_metadata else []):
            journal.enqueue(path, PREFIX_URI, server.endpoint_url, location.bucket, location.key(path.name), False)
        assert Uploader(journal).drain() is None
    finally:
        journal.close()
    return location.uri


@pytest.fixture
def server(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[S3Server]:
    """A nanio server with the bucket ``bags``; its AWS environment set here (and so in the commands run)."""
    with S3Server(tmp_path / "store") as running:
        for name, value in running.env().items():
            monkeypatch.setenv(name, value)
        monkeypatch.delenv("AWS_PROFILE", raising=False)
        running.client().create_bucket(Bucket=BUCKET)
        yield running


@pytest.fixture
def split_bag(tmp_path: Path, server: S3Server) -> tuple[Path, str]:
    """A bag of three files or more (about 3 MB) uploaded: (the local bag, its URI)."""
    bag = write_bag(tmp_path / "robot" / "run1", 3 * MiB, max_bagfile_size=MiB)
    return bag, upload(server, bag)


def bag_files(bag: Path) -> list[str]:
    return sorted(path.name for path in bag.iterdir())


# --- download ---------------------------------------------------------------------------------------------
def test_a_bag_downloads_byte_identical_and_a_second_run_fetches_nothing(
        tmp_path: Path, server: S3Server, split_bag: tuple[Path, str]) -> None:
    bag, uri = split_bag
    count = len(bag_files(bag))
    assert count >= 4  # three storage files or more, and metadata.yaml
    first = cli("bag", "download", uri, str(tmp_path / "here"), "--endpoint-url", server.endpoint_url)
    assert first.returncode == 0, first.stderr
    copy = tmp_path / "here" / bag.name
    assert bag_files(copy) == bag_files(bag)
    assert {name: sha256(copy / name) for name in bag_files(copy)} == \
           {name: sha256(bag / name) for name in bag_files(bag)}
    lines = first.stdout.splitlines()
    assert lines[-2].startswith(f"{METADATA_FILENAME}: ") and lines[-2].endswith("verified")  # last
    total = sum((bag / name).stat().st_size for name in bag_files(bag))
    assert lines[-1] == f"{copy}: {count} files, {total} bytes fetched"

    again = cli("bag", "download", uri, str(tmp_path / "here"), "--endpoint-url", server.endpoint_url)
    assert again.returncode == 0, again.stderr
    assert again.stdout.count("already here, verified") == count
    assert again.stdout.splitlines()[-1] == f"{copy}: {count} files, 0 bytes fetched, {count} already here"


def test_a_partial_file_is_continued_and_one_that_does_not_verify_is_not_kept(
        tmp_path: Path, server: S3Server, split_bag: tuple[Path, str]) -> None:
    bag, uri = split_bag
    name = bag_files(bag)[0]
    original = (bag / name).read_bytes()
    copy = tmp_path / "here" / bag.name
    copy.mkdir(parents=True)
    (copy / f"{name}.part").write_bytes(original[:len(original) // 3])  # a download cut at a third

    resumed = cli("bag", "download", uri, str(tmp_path / "here"), "--endpoint-url", server.endpoint_url)
    assert resumed.returncode == 0, resumed.stderr
    fetched = len(original) - len(original) // 3
    assert f"{name}: {fetched} bytes fetched, resumed after {len(original) // 3} bytes, verified" in resumed.stdout
    assert sha256(copy / name) == hashlib.sha256(original).hexdigest()
    assert not list(copy.glob("*.part"))

    (copy / name).unlink()
    (copy / f"{name}.part").write_bytes(b"x" * 1000)  # not the beginning of this object
    wrong = cli("bag", "download", uri, str(tmp_path / "here"), "--endpoint-url", server.endpoint_url)
    assert wrong.returncode == 1
    assert f"{name} did not verify" in wrong.stderr and "resumed from byte 1000" in wrong.stderr
    assert not (copy / name).exists() and not (copy / f"{name}.part").exists()
    assert cli("bag", "download", uri, str(tmp_path / "here"), "--endpoint-url", server.endpoint_url).returncode == 0
    assert sha256(copy / name) == hashlib.sha256(original).hexdigest()


def test_a_file_here_with_other_content_is_not_overwritten(
        tmp_path: Path, server: S3Server, split_bag: tuple[Path, str]) -> None:
    bag, uri = split_bag
    copy = tmp_path / "here" / bag.name
    copy.mkdir(parents=True)
    (copy / METADATA_FILENAME).write_text("mine")
    result = cli("bag", "download", uri, str(tmp_path / "here"), "--endpoint-url", server.endpoint_url)
    assert result.returncode == 1
    assert f"{copy / METADATA_FILENAME} exists and holds other content" in result.stderr
    assert (copy / METADATA_FILENAME).read_text() == "mine"


def test_a_download_cut_by_a_server_kill_resumes_after_the_restart(tmp_path: Path, server: S3Server) -> None:
    """A 12 MiB file (a multipart object: its ETag is the MD5 of its parts' MD5s) is cut when the server is
    SIGKILLed mid-download; after the restart on the same port and data, only the rest is fetched."""
    from baglib.upload.client import make_client
    from baglib.upload.download import download_bag

    bag = write_bag(tmp_path / "robot" / "big", 12 * MiB)
    location = parse_s3_uri(upload(server, bag))
    name = next(path.name for path in bag.iterdir() if path.suffix == ".mcap")
    size = (bag / name).stat().st_size
    assert "-" in server.client().head_object(Bucket=BUCKET, Key=location.key(name))["ETag"]
    client = make_client(server.endpoint_url)

    with pytest.raises(Exception):  # noqa: B017,PT011 - whatever the client raises for a connection cut
        download_bag(client, location, tmp_path / "here", progress=lambda fetched: server.kill())
    partial = tmp_path / "here" / bag.name / f"{name}.part"
    held = partial.stat().st_size
    assert 0 < held < size

    server.start()
    done = {file.name: file for file in download_bag(client, location, tmp_path / "here")}
    assert done[name].resumed == held and done[name].fetched == size - held
    assert sha256(tmp_path / "here" / bag.name / name) == sha256(bag / name)


def test_a_bag_without_metadata_in_the_store_is_refused(tmp_path: Path, server: S3Server) -> None:
    bag = write_bag(tmp_path / "robot" / "cut", MiB)
    uri = upload(server, bag, with_metadata=False)
    result = cli("bag", "download", uri, str(tmp_path / "here"), "--endpoint-url", server.endpoint_url)
    assert result.returncode == 1
    assert f"{uri} is not a complete bag in the store: no {METADATA_FILENAME} there" in result.stderr
    assert not (tmp_path / "here").exists() or not any((tmp_path / "here").rglob("*"))
    info = cli("bag", "info", uri, "--endpoint-url", server.endpoint_url)
    assert info.returncode == 1 and f"it has no {METADATA_FILENAME}" in info.stderr


@pytest.mark.parametrize("fault", ["credentials", "bucket", "endpoint"])
def test_store_faults_are_worded_errors(tmp_path: Path, server: S3Server, split_bag: tuple[Path, str],
                                        monkeypatch: pytest.MonkeyPatch, fault: str) -> None:
    _, uri = split_bag
    endpoint = server.endpoint_url
    expected = {"credentials": "the store refused the credentials", "bucket": "the bucket does not exist",
                "endpoint": "the endpoint cannot be reached"}[fault]
    if fault == "credentials":
        monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "not-the-secret")
    elif fault == "bucket":
        uri = uri.replace(f"s3://{BUCKET}/", "s3://no-such-bucket/")
    else:
        server.kill()  # nothing listens on its port any more
    for command in (("bag", "download", uri, str(tmp_path / "here")), ("bag", "info", uri)):
        result = cli(*command, "--endpoint-url", endpoint)
        assert result.returncode == 1, result.stdout
        assert expected in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "here").exists()


# --- info ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("options", [(), ("--sort", "count"), ("-t",)])
def test_info_of_a_bag_in_the_store_prints_what_info_prints_here(
        server: S3Server, split_bag: tuple[Path, str], options: tuple[str, ...]) -> None:
    bag, uri = split_bag
    here = cli("bag", "info", str(bag), *options)
    there = cli("bag", "info", uri, "--endpoint-url", server.endpoint_url, *options)
    assert here.returncode == 0 and there.returncode == 0, there.stderr
    assert there.stdout == here.stdout
    assert "Files:" in there.stdout or options == ("-t",)


def test_info_of_one_mcap_object_reads_its_summary_by_range(tmp_path: Path, server: S3Server) -> None:
    from baglib.read.reader import BagReader
    from baglib.tools.info import file_summary, format_bag_info
    from baglib.upload.client import make_client
    from baglib.upload.remote_read import RangedFile

    bag = write_bag(tmp_path / "robot" / "one", 4 * MiB)
    location = parse_s3_uri(upload(server, bag))
    name = next(path.name for path in bag.iterdir() if path.suffix == ".mcap")
    uri = f"s3://{BUCKET}/{location.key(name)}"
    with RangedFile(make_client(server.endpoint_url), BUCKET, location.key(name)) as source, \
            BagReader(uri, source=source) as reader:
        remote = format_bag_info(uri, summary=file_summary(reader, source.size))
        size = source.size
        assert source.fetched < size // 20, (source.fetched, source.requests, size)
    assert remote == format_bag_info(bag / name)
    assert size == (bag / name).stat().st_size

    here, there = cli("bag", "info", str(bag / name)), cli("bag", "info", uri, "--endpoint-url", server.endpoint_url)
    assert there.returncode == 0, there.stderr
    assert there.stdout == here.stdout
    verbose = cli("bag", "info", uri, "--endpoint-url", server.endpoint_url, "--verbose")
    assert verbose.returncode == 1 and "download the bag first" in verbose.stderr
