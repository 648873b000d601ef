"""Downloading a bag from the store: resumable, each file verified before it takes its name, ``metadata.yaml`` last.

Only a bag complete in the store is taken: one whose ``metadata.yaml`` is there (the uploader puts it there last).
Each object goes to ``<file>.part`` first; a ``.part`` left by a download that was cut (a network drop, a server
restart, Ctrl-C) is continued with a ranged GET from where it ends, ``If-Match`` the object's ETag. Before the
rename, the file is verified against the object: its size and the ETag its bytes give
(:func:`~baglib.upload.digests.matches_object`, with the part size the uploader recorded). A file that does not
verify is an error naming it, and its ``.part`` is removed, so the next run fetches it whole; it never takes the
file's name. A file already here that verifies is not fetched again; one here that holds something else is
refused, never overwritten. ``metadata.yaml`` comes last, so a local bag directory with a ``metadata.yaml`` is a
complete download, as a bag in the store is complete with its own.
"""
from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

from baglib.format.metadata import METADATA_FILENAME
from baglib.upload.client import UploadError
from baglib.upload.digests import matches_object
from baglib.upload.location import S3Location
from baglib.upload.remote_read import object_sizes

#: The suffix of a file while it is being downloaded.
PARTIAL_SUFFIX = ".part"
#: Bytes written at a time while streaming an object.
CHUNK = 1 << 20


@dataclass(frozen=True)
class Downloaded:
    """What downloading one file took: its size, the bytes fetched now and those a ``.part`` already held, and
    whether the file was here already (verified, nothing fetched)."""

    name: str
    size: int
    fetched: int = 0
    resumed: int = 0
    already_here: bool = False


def bag_name(location: S3Location) -> str:
    """The bag's directory name: the last component of ``location``'s prefix."""
    if not location.prefix:
        raise UploadError(f"{location.uri} names no bag: give s3://BUCKET/PREFIX/BAG", permanent=True)
    return location.prefix.rsplit("/", 1)[-1]


def bag_files(client: Any, location: S3Location) -> list[str]:
    """The bag's files in the store, ``metadata.yaml`` last; UploadError if the bag is not complete there."""
    names = sorted(object_sizes(client, location))
    if METADATA_FILENAME not in names:
        found = f"only {', '.join(names)}" if names else "nothing"
        raise UploadError(f"{location.uri} is not a complete bag in the store: no {METADATA_FILENAME} there "
                          f"({found}; an upload still under way or cut short?): not downloaded", permanent=True)
    for name in names:
        if PurePosixPath(name).is_absolute() or any(part in ("", ".", "..") for part in name.split("/")):
            raise UploadError(f"{location.uri} holds the key {name!r}, which is no file name inside a bag: "
                              "not downloaded", permanent=True)
    names.remove(METADATA_FILENAME)
    return [*names, METADATA_FILENAME]


def download_file(client: Any, location: S3Location, name: str, target: Path,
                  progress: Callable[[int], None] = lambda fetched: None) -> Downloaded:
    """Download ``location``/``name`` to ``target`` through ``target.part``, resuming it, verified (see module
    docstring); ``progress(bytes)`` after each chunk written. Raises UploadError on a mismatch."""
    source = f"s3://{location.bucket}/{location.key(name)}"
    head = client.head_object(Bucket=location.bucket, Key=location.key(name))
    size = int(head["ContentLength"])
    if target.exists():
        if matches_object(target, head):
            return Downloaded(name, size, already_here=True)
        raise UploadError(f"{target} exists and holds other content than {source}: not overwritten",
                          permanent=True)
    partial = target.with_name(target.name + PARTIAL_SUFFIX)
    resumed = partial.stat().st_size if partial.exists() else 0
    if resumed > size:  # not a beginning of this object: start over
        partial.unlink()
        resumed = 0
    fetched = 0
    with open(partial, "ab") as output:
        if resumed < size:
            answer = client.get_object(Bucket=location.bucket, Key=location.key(name), IfMatch=head["ETag"],
                                       Range=f"bytes={resumed}-{size - 1}")
            for chunk in answer["Body"].iter_chunks(CHUNK):
                output.write(chunk)
                fetched += len(chunk)
                progress(len(chunk))
        output.flush()
        os.fsync(output.fileno())
    if not matches_object(partial, head):
        partial.unlink()
        how = f"the download resumed from byte {resumed}" if resumed else "the download"
        raise UploadError(f"{name} did not verify: {source} is {size} bytes with ETag {head['ETag']}, {how} is "
                          "not the same; its partial file was removed, run the download again", permanent=True)
    os.replace(partial, target)
    return Downloaded(name, size, fetched, resumed)


def download_bag(client: Any, location: S3Location, directory: Path,
                 on_file: Callable[[Downloaded], None] = lambda done: None,
                 progress: Callable[[int], None] = lambda fetched: None) -> list[Downloaded]:
    """Download the bag at ``location`` into ``directory``/<bag> (created), ``metadata.yaml`` last; ``on_file``
    after each file. Raises UploadError (a bag not complete in the store, a file that does not verify) or the
    client's errors (to be worded by :func:`~baglib.upload.client.describe`)."""
    bag = directory / bag_name(location)
    done = []
    for name in bag_files(client, location):
        target = bag / name
        target.parent.mkdir(parents=True, exist_ok=True)
        done.append(download_file(client, location, name, target, progress))
        on_file(done[-1])
    return done
