"""The boto3 client behind :class:`~api.service.store.s3.S3Store`, and what its errors mean.

Configuration comes from :class:`Settings` first and the standard AWS variables second
(``AWS_ENDPOINT_URL_S3``/``AWS_ENDPOINT_URL``, ``AWS_REGION``/``AWS_DEFAULT_REGION``,
``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``/``AWS_SESSION_TOKEN``, ``AWS_PROFILE``,
instance and task roles): boto3's own chain, so whatever points the AWS CLI at a bucket
points Glint at it too. Every request has a connect and a read timeout, so an unreachable
endpoint is an error after seconds, never a hang.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from api.service.store.base import StoreUnavailableError

# S3 error codes that say the credentials (or their rights) are the problem
AUTH_CODES = frozenset(
    {
        "403",
        "AccessDenied",
        "InvalidAccessKeyId",
        "SignatureDoesNotMatch",
        "ExpiredToken",
        "InvalidToken",
        "InvalidClientTokenId",
        "AuthorizationHeaderMalformed",
        "AllAccessDisabled",
    }
)
MISSING_BUCKET_CODES = frozenset({"NoSuchBucket"})
NOT_FOUND_CODES = frozenset({"404", "NoSuchKey", "NotFound"})


@dataclass(frozen=True)
class S3Location:
    """``s3://bucket/prefix``: the bucket and the key prefix (no slashes at its ends)."""

    bucket: str
    prefix: str

    @classmethod
    def parse(cls, url: str) -> S3Location:
        parts = urlsplit(url)
        if parts.scheme != "s3" or not parts.netloc:
            raise ValueError(f"not an s3://BUCKET[/PREFIX] URL: {url!r}")
        return cls(parts.netloc, parts.path.strip("/"))

    def key(self, key: str) -> str:
        return f"{self.prefix}/{key}" if self.prefix else key

    def unkey(self, s3_key: str) -> str:
        return s3_key[len(self.prefix) + 1 :] if self.prefix else s3_key

    def __str__(self) -> str:
        return f"s3://{self.bucket}/{self.prefix}" if self.prefix else f"s3://{self.bucket}"


def endpoint_url(configured: str | None) -> str | None:
    """The endpoint in force: the setting, else the AWS variables (boto3 reads them too)."""
    return (
        configured
        or os.environ.get("AWS_ENDPOINT_URL_S3")
        or os.environ.get("AWS_ENDPOINT_URL")
        or None
    )


def make_client(
    *,
    endpoint: str | None,
    region: str | None,
    access_key_id: str | None,
    secret_access_key: str | None,
    addressing_style: str,
    timeout_s: float,
    attempts: int,
    pool: int = 16,
) -> Any:
    """A boto3 S3 client; ``attempts`` counts botocore's own retries of one request."""
    import boto3
    from botocore.config import Config

    style = addressing_style
    if style == "auto" and endpoint:
        style = "path"  # MinIO and most S3-compatible servers: no per-bucket host names
    config = Config(
        connect_timeout=timeout_s,
        read_timeout=timeout_s,
        retries={"max_attempts": attempts, "mode": "standard"},
        s3={"addressing_style": style},
        max_pool_connections=pool,
        # checksums only where S3 requires them: older S3-compatible servers reject the
        # CRC headers newer botocore adds by default
        request_checksum_calculation="when_required",
        response_checksum_validation="when_required",
    )
    explicit = bool(access_key_id and secret_access_key)  # half a pair: the AWS chain
    session = boto3.session.Session(
        aws_access_key_id=access_key_id if explicit else None,
        aws_secret_access_key=secret_access_key if explicit else None,
        region_name=region or None,
    )
    return session.client("s3", endpoint_url=endpoint, config=config)


def error_code(exc: BaseException) -> str | None:
    """The S3 error code of a botocore ClientError (``NoSuchKey``, ``403``...), else None."""
    response = getattr(exc, "response", None)
    if not isinstance(response, dict):
        return None
    code = response.get("Error", {}).get("Code")
    return str(code) if code is not None else None


def unavailable(exc: BaseException, where: str) -> StoreUnavailableError | None:
    """The :class:`StoreUnavailableError` that ``exc`` amounts to, or None when it is
    about the request itself (a missing key, a bad argument) rather than the store."""
    from botocore.exceptions import (
        BotoCoreError,
        ClientError,
        NoCredentialsError,
        PartialCredentialsError,
    )

    if type(exc).__name__ == "S3UploadFailedError" and exc.__context__ is not None:
        return unavailable(exc.__context__, where)  # boto3's transfer manager wraps the cause
    if isinstance(exc, NoCredentialsError | PartialCredentialsError):
        return StoreUnavailableError(f"no credentials for {where}: {exc}")
    if isinstance(exc, ClientError):
        code = error_code(exc) or "?"
        status = exc.response.get("ResponseMetadata", {}).get("HTTPStatusCode", 0)
        if code in AUTH_CODES:
            return StoreUnavailableError(f"{where} refused the credentials ({code})")
        if code in MISSING_BUCKET_CODES:
            return StoreUnavailableError(f"{where}: the bucket does not exist ({code})")
        if isinstance(status, int) and status >= 500:
            return StoreUnavailableError(f"{where} failed ({code}, HTTP {status})")
        return None
    if isinstance(exc, BotoCoreError | OSError):
        return StoreUnavailableError(f"{where} is unreachable ({type(exc).__name__}: {exc})")
    try:  # a body read cut short surfaces as urllib3's own error
        from urllib3.exceptions import HTTPError as Urllib3Error
    except ImportError:  # pragma: no cover - urllib3 ships with botocore
        return None
    if isinstance(exc, Urllib3Error):
        return StoreUnavailableError(f"{where} is unreachable ({type(exc).__name__}: {exc})")
    return None
