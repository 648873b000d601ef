"""The S3 client (botocore, the core of the AWS SDK boto3) and what its errors mean to a person.

Credentials come from the AWS SDK's standard chain only (``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``, ``AWS_PROFILE``
with ``~/.aws/credentials`` and ``~/.aws/config``): nothing here takes a secret as an argument, so none can end up
in a parameter, a log line or a bag. An explicit endpoint (any S3-compatible store) is addressed path-style, as
local servers need. botocore's default CRC32 checksums on every request are turned off
(``request_checksum_calculation="when_required"``): several S3-compatible servers reject them, and every part
carries its Content-MD5 instead, which the transfer checks against the ETag the server answers.

Every client has a botocore session of its own (the credentials are looked up anew each time), and they share one
loader of botocore's service descriptions: S3's is a large JSON document, whose parsing cost each new session 60 to
100 ms of CPU (a process that makes several clients, an upload worker per endpoint and a bag's listing, paid it each
time); with the loader shared, a client after the first takes about 12 ms.

Timeouts are short on purpose: a server that stalls must show up as an error in ``~/get_stats`` within seconds,
and botocore does not retry on its own: the upload queue retries with a back-off of its own.
"""
from __future__ import annotations

import socket
from typing import Any

import botocore.exceptions
import botocore.loaders
import botocore.session
from botocore.config import Config

#: Seconds to connect and to wait for each read from the server.
CONNECT_TIMEOUT = 5.0
READ_TIMEOUT = 10.0

#: botocore's reader of its service descriptions, with their cache: shared by the clients this process makes.
_LOADER = botocore.loaders.create_loader()

#: Error codes that mean the credentials are wrong or not allowed to write here.
_CREDENTIAL_CODES = {"InvalidAccessKeyId", "SignatureDoesNotMatch", "AccessDenied", "InvalidToken",
                     "ExpiredToken", "AuthorizationHeaderMalformed", "403"}


class UploadError(Exception):
    """An upload step failed; the message says what and is safe to log (it never holds a credential).

    ``permanent``: retrying cannot help until a person changes something (credentials, bucket, a conflicting
    object); the queue still retries, slower, since a person may fix it while the recorder runs.
    """

    def __init__(self, message: str, permanent: bool = False) -> None:
        super().__init__(message)
        self.permanent = permanent


def make_client(endpoint_url: str = "", read_timeout: float = READ_TIMEOUT) -> Any:
    """An S3 client for ``endpoint_url`` (empty: what the AWS configuration says) with the standard credential
    chain; raises UploadError when no credentials are configured at all."""
    session = botocore.session.get_session()  # a new one: its own credentials and configuration
    session.register_component("data_loader", _LOADER)
    if session.get_credentials() is None:
        raise UploadError("no AWS credentials: set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY, AWS_PROFILE, or "
                          "~/.aws/credentials", permanent=True)
    config = Config(connect_timeout=CONNECT_TIMEOUT, read_timeout=read_timeout,
                    retries={"total_max_attempts": 1, "mode": "standard"},
                    request_checksum_calculation="when_required", response_checksum_validation="when_required",
                    s3={"addressing_style": "path"} if endpoint_url else None)
    return session.create_client("s3", endpoint_url=endpoint_url or None,
                                 region_name=session.get_config_variable("region") or "us-east-1", config=config)


def is_not_found(error: botocore.exceptions.ClientError) -> bool:
    """The request failed because the key (or the multipart upload) is not there."""
    return str(error.response.get("Error", {}).get("Code")) in ("404", "NoSuchKey", "NotFound", "NoSuchUpload")


def describe(error: BaseException, what: str) -> UploadError:
    """An UploadError saying, in words, why ``what`` failed (wrong credentials, a missing bucket, an
    unreachable or stalled endpoint, a server error)."""
    if isinstance(error, UploadError):
        return error
    if isinstance(error, botocore.exceptions.ClientError):
        info = error.response.get("Error", {})
        code = str(info.get("Code", ""))
        status = error.response.get("ResponseMetadata", {}).get("HTTPStatusCode", 0)
        if code in _CREDENTIAL_CODES:
            return UploadError(f"{what}: the store refused the credentials ({code}): check AWS_ACCESS_KEY_ID / "
                               "AWS_SECRET_ACCESS_KEY or the profile", permanent=True)
        if code == "NoSuchBucket":
            return UploadError(f"{what}: the bucket does not exist ({code})", permanent=True)
        if status >= 500:
            return UploadError(f"{what}: the server answered {status} ({code or 'no code'})")
        return UploadError(f"{what}: {code or status}: {info.get('Message', '')}".rstrip(": "))
    if isinstance(error, botocore.exceptions.NoCredentialsError):
        return UploadError(f"{what}: no AWS credentials", permanent=True)
    if isinstance(error, (botocore.exceptions.ReadTimeoutError, socket.timeout, TimeoutError)):
        return UploadError(f"{what}: the server stopped answering (read timeout)")
    if isinstance(error, (botocore.exceptions.EndpointConnectionError, botocore.exceptions.ConnectionError,
                          ConnectionError)):
        return UploadError(f"{what}: the endpoint cannot be reached ({type(error).__name__})")
    if isinstance(error, botocore.exceptions.HTTPClientError):  # the connection broke in the middle of a request
        return UploadError(f"{what}: the endpoint closed the connection ({type(error).__name__})")
    return UploadError(f"{what}: {type(error).__name__}: {error}")
