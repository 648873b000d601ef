"""Where bags go: an ``s3://BUCKET/PREFIX`` URI, checked, and the object key of each bag file under it.

The key layout is the bag's own, ``PREFIX/<bag>/<file>``, so a bucket holds bags as a bag root holds them and a
reader that lists ``PREFIX/`` finds them. Credentials never travel in the URI: one that carries a user, a
password or a query (a presigned URL's signature) is refused, since the URI is a parameter that is echoed in logs,
``~/get_stats`` and the bag's own metadata.
"""
from __future__ import annotations

import re
import urllib.parse
from dataclasses import dataclass

#: S3's bucket naming rules (3-63 characters: lower-case letters, digits, dots and hyphens, starting and ending
#: with a letter or digit); a name outside them is refused before any request is made.
_BUCKET = re.compile(r"^[a-z0-9][a-z0-9.-]{1,61}[a-z0-9]$")


@dataclass(frozen=True)
class S3Location:
    """A bucket and a key prefix (no leading or trailing slash; may be empty)."""

    bucket: str
    prefix: str = ""

    @property
    def uri(self) -> str:
        return f"s3://{self.bucket}/{self.prefix}" if self.prefix else f"s3://{self.bucket}"

    def child(self, *names: str) -> S3Location:
        """The location ``names`` below this one (a bag's location is its prefix's child)."""
        parts = [self.prefix, *names] if self.prefix else list(names)
        return S3Location(self.bucket, "/".join(part.strip("/") for part in parts if part.strip("/")))

    def key(self, name: str) -> str:
        """The object key of the file ``name`` at this location."""
        return f"{self.prefix}/{name}" if self.prefix else name


def parse_s3_uri(uri: str, label: str = "upload.uri") -> S3Location:
    """The location ``uri`` names; ValueError naming ``label`` and what is wrong with it otherwise."""
    parsed = urllib.parse.urlsplit(uri)
    if parsed.scheme != "s3":
        raise ValueError(f"{label} {uri!r} is not an s3:// URI (s3://BUCKET/PREFIX)")
    if "@" in parsed.netloc or parsed.query or parsed.fragment:
        raise ValueError(f"{label} must not carry credentials or a query (a user, a password or a signature): "
                         "give them through the AWS environment, ~/.aws/credentials or a profile")
    if not _BUCKET.match(parsed.netloc):
        raise ValueError(f"{label} {uri!r}: {parsed.netloc!r} is not a valid bucket name (3-63 lower-case "
                         "letters, digits, dots and hyphens)")
    prefix = parsed.path.strip("/")
    if any(part in ("", ".", "..") for part in prefix.split("/")) and prefix:
        raise ValueError(f"{label} {uri!r}: the prefix has an empty, '.' or '..' component")
    return S3Location(parsed.netloc, prefix)
