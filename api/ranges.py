"""Serving a stored object over HTTP: ETag revalidation and single byte ranges.

The bytes come from the artifact store (``read_range``: a file read, or one ranged GET
from the bucket streamed through), so the owner check of the route guards every byte
and clients need no access to the store.

``If-None-Match`` answers 304; ``Range: bytes=a-b`` (also ``a-`` and ``-n``) answers
206 with ``Content-Range``; a range outside the file (or a malformed one) answers 416
with ``Content-Range: bytes */size``. Multi-range requests get the whole file (200),
which RFC 9110 allows; ``If-Range`` with a different ETag does the same.
"""

from __future__ import annotations

import re

from starlette.requests import Request
from starlette.responses import Response, StreamingResponse

from api.problems import ApiError
from api.service.store import ArtifactStore

_RANGE = re.compile(r"^\s*(\d*)\s*-\s*(\d*)\s*$")


class RangeNotSatisfiableError(ApiError):
    def __init__(self, size: int, detail: str) -> None:
        super().__init__(
            416, "range-not-satisfiable", detail, headers={"Content-Range": f"bytes */{size}"}
        )


def etag_matches(header: str | None, etag: str) -> bool:
    """Weak comparison (RFC 9110 §13.1.2), as If-None-Match requires."""
    if not header:
        return False
    if header.strip() == "*":
        return True
    bare = etag.removeprefix("W/")
    return any(t.strip().removeprefix("W/") == bare for t in header.split(","))


def parse_range(header: str, size: int) -> tuple[int, int] | None:
    """(start, end inclusive) of a single ``bytes=`` range; None to serve the whole file."""
    unit, _, spec = header.partition("=")
    if unit.strip().lower() != "bytes":
        return None  # unknown units are ignored
    if "," in spec:
        return None  # several ranges: the whole file instead of multipart/byteranges
    m = _RANGE.match(spec)
    if not m or (not m.group(1) and not m.group(2)):
        raise RangeNotSatisfiableError(size, f"malformed range '{header}'")
    first, last = m.group(1), m.group(2)
    if not first:  # suffix: the last n bytes
        n = int(last)
        if n == 0 or size == 0:
            raise RangeNotSatisfiableError(size, f"range '{header}' selects no bytes")
        return max(size - n, 0), size - 1
    start = int(first)
    end = int(last) if last else size - 1
    if end < start:
        raise RangeNotSatisfiableError(size, f"range '{header}' ends before it starts")
    if start >= size:
        raise RangeNotSatisfiableError(size, f"range '{header}' starts beyond the {size}-byte file")
    return start, min(end, size - 1)


def stored_response(
    request: Request,
    store: ArtifactStore,
    key: str,
    *,
    size: int,
    etag: str,
    content_type: str,
    filename: str,
) -> Response:
    """200, 206, 304 or 416 for the object ``key`` (``size`` bytes) according to the
    request's conditional headers."""
    headers = {
        "ETag": etag,
        "Accept-Ranges": "bytes",
        "Cache-Control": "private, no-cache",
        "Content-Disposition": f'inline; filename="{filename}"',
    }
    if etag_matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=304, headers=headers)
    start, end, status = 0, size - 1, 200
    range_header = request.headers.get("range")
    if_range = request.headers.get("if-range")
    if range_header and (if_range is None or if_range.strip() == etag):
        rng = parse_range(range_header, size)
        if rng is not None:
            start, end = rng
            status = 206
            headers["Content-Range"] = f"bytes {start}-{end}/{size}"
    length = max(end - start + 1, 0)
    headers["Content-Length"] = str(length)
    # a blocking iterator: Starlette pulls it on worker threads
    return StreamingResponse(
        store.read_range(key, start, length),
        status_code=status,
        media_type=content_type,
        headers=headers,
    )
