"""Typed exceptions: the API's RFC 9457 problem details, and the client's own failures.

Every API error is ``application/problem+json`` with a stable ``type``
(``urn:glint:problem:<slug>``) and, where fields are at fault, ``errors`` naming each
one. :func:`from_response` turns such a body into the subclass for its status (or, for
the few types a client acts on, for its slug), so callers can ``except NotFound`` or
read ``exc.field`` instead of parsing JSON.
"""

# The classes are named after the HTTP statuses they stand for (NotFound, Conflict, ...),
# as callers read them in `except` clauses, not with an Error suffix.
# ruff: noqa: N818

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, ClassVar

import httpx

PROBLEM_PREFIX = "urn:glint:problem:"


class GlintClientError(Exception):
    """Anything the client raises on purpose; ``str()`` is a sentence a user can act on."""


class ServerUnreachable(GlintClientError):
    """No HTTP answer at all (refused, DNS, timeouts) after the retries: a network or
    server problem, not a problem of the request."""


class IntegrityError(GlintClientError):
    """A downloaded file's SHA-256 differs from the one the server listed, twice in a row."""


class JobFailed(GlintClientError):
    """``wait()`` saw the job end ``failed`` (``job`` holds it; ``error`` says why)."""

    def __init__(self, job: dict[str, Any]) -> None:
        self.job = job
        super().__init__(f"job {job.get('id')} failed: {job.get('error') or 'no reason given'}")


class JobCancelled(GlintClientError):
    """``wait()`` saw the job end ``cancelled``."""

    def __init__(self, job: dict[str, Any]) -> None:
        self.job = job
        super().__init__(f"job {job.get('id')} was cancelled")


@dataclass(frozen=True)
class FieldProblem:
    """One field at fault: a dotted path into the request (``body.config.iterations``) or,
    for scene validation, the field inside ``file`` (a path relative to the scene)."""

    field: str | None
    message: str
    file: str | None = None

    def __str__(self) -> str:
        where = ": ".join(p for p in (self.file, self.field) if p)
        return f"{where}: {self.message}" if where else self.message


class GlintAPIError(GlintClientError):
    """An error answer of the API. ``slug`` is ``type`` without its URN prefix."""

    status_code: ClassVar[int | None] = None

    def __init__(
        self,
        status: int,
        slug: str,
        detail: str,
        *,
        title: str = "",
        instance: str | None = None,
        errors: list[FieldProblem] | None = None,
        body: dict[str, Any] | None = None,
        method: str = "",
        url: str = "",
    ) -> None:
        self.status = status
        self.slug = slug
        self.title = title
        self.detail = detail
        self.instance = instance
        self.errors = errors or []
        self.body = body or {}
        self.method = method
        self.url = url
        super().__init__(self._message())

    @property
    def type(self) -> str:
        return PROBLEM_PREFIX + self.slug

    @property
    def field(self) -> str | None:
        """The first field at fault (``None`` when the error names none)."""
        return next((e.field for e in self.errors if e.field), None)

    @property
    def file(self) -> str | None:
        """The first scene file at fault (scene validation, archive members)."""
        return next((e.file for e in self.errors if e.file), None)

    def _message(self) -> str:
        text = f"{self.status} {self.slug}: {self.detail or self.title}"
        named = [str(e) for e in self.errors if e.field or e.file]
        if named and not all(n in self.detail for n in named):
            text += " [" + "; ".join(named) + "]"
        return text


class BadRequest(GlintAPIError):
    status_code = 400


class Unauthorized(GlintAPIError):
    """401: the key is missing, unknown or revoked."""

    status_code = 401


class Forbidden(GlintAPIError):
    """403: the key's scope does not allow this (``read`` keys cannot create)."""

    status_code = 403


class NotFound(GlintAPIError):
    """404: no such id, or another owner's."""

    status_code = 404


class Conflict(GlintAPIError):
    """409: the resource's state forbids it (``slug`` says which, e.g. ``scene-committed``)."""

    status_code = 409


class OffsetMismatch(Conflict):
    """409 ``offset-mismatch``: a chunk was sent for another offset than the server's;
    ``offset`` is where the server is, so the upload continues from there."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        raw = self.body.get("offset")
        self.offset: int | None = raw if isinstance(raw, int) else None


class TooLarge(GlintAPIError):
    """413: a file, the scene or an archive is over a server limit."""

    status_code = 413


class UnsupportedMediaType(GlintAPIError):
    status_code = 415


class RangeNotSatisfiable(GlintAPIError):
    status_code = 416


class ValidationError(GlintAPIError):
    """422: content is invalid; ``errors`` (and ``field``/``file``) name what."""

    status_code = 422


class ChecksumMismatch(ValidationError):
    """422 ``checksum-mismatch``: the joined upload's SHA-256 is not the one declared
    (the file changed while it was sent); the server reset the upload to offset 0."""


class IdempotencyKeyReused(ValidationError):
    """422 ``idempotency-key-reused``: the ``Idempotency-Key`` was already used with
    another body (a bug of the caller: each distinct create needs a key of its own)."""


class TooManyRequests(GlintAPIError):
    status_code = 429


class ServerError(GlintAPIError):
    """5xx: a server bug (500) or a dependency that is down (503)."""

    status_code = 500


class ServiceUnavailable(ServerError):
    """503: the queue, database or store is down (``slug`` says which)."""

    status_code = 503


_BY_STATUS: dict[int, type[GlintAPIError]] = {
    cls.status_code: cls
    for cls in (
        BadRequest,
        Unauthorized,
        Forbidden,
        NotFound,
        Conflict,
        TooLarge,
        UnsupportedMediaType,
        RangeNotSatisfiable,
        ValidationError,
        TooManyRequests,
        ServerError,
        ServiceUnavailable,
    )
    if cls.status_code is not None
}
_BY_SLUG: dict[str, type[GlintAPIError]] = {
    "offset-mismatch": OffsetMismatch,
    "checksum-mismatch": ChecksumMismatch,
    "idempotency-key-reused": IdempotencyKeyReused,
}


def error_class(status: int, slug: str) -> type[GlintAPIError]:
    if slug in _BY_SLUG:
        return _BY_SLUG[slug]
    if status in _BY_STATUS:
        return _BY_STATUS[status]
    return ServerError if status >= 500 else GlintAPIError


def _field_problems(raw: Any) -> list[FieldProblem]:
    if not isinstance(raw, list):
        return []
    out = []
    for e in raw:
        if isinstance(e, dict):
            out.append(
                FieldProblem(
                    field=e.get("field"), message=str(e.get("message", "")), file=e.get("file")
                )
            )
    return out


def from_response(response: httpx.Response) -> GlintAPIError:
    """The typed exception for an error response (the body must have been read).

    A body that is not problem+json (a proxy's HTML page, say) still gives the class for
    its status, with the start of the body as ``detail``.
    """
    status = response.status_code
    body: dict[str, Any] = {}
    try:
        parsed = json.loads(response.content or b"null")
        if isinstance(parsed, dict):
            body = parsed
    except (ValueError, UnicodeDecodeError):
        pass
    raw_type = body.get("type")
    if isinstance(raw_type, str) and raw_type.startswith(PROBLEM_PREFIX):
        slug = raw_type[len(PROBLEM_PREFIX) :]
    else:
        slug = f"http-{status}"
    detail = body.get("detail")
    if not isinstance(detail, str):
        detail = "" if body else response.text[:200].strip()
    cls = error_class(status, slug)
    request = response.request
    return cls(
        status,
        slug,
        detail,
        title=str(body.get("title") or response.reason_phrase),
        instance=body.get("instance"),
        errors=_field_problems(body.get("errors")),
        body=body,
        method=request.method,
        url=str(request.url),
    )
