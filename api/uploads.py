"""Request bodies streamed into the store: multipart parts and whole archives.

Nothing is held in memory beyond one network chunk: the multipart parser runs
incrementally on ``request.stream()`` and every part goes to a pending store write
as it arrives. Sizes are checked as bytes arrive (``Content-Length`` first when the
client sends one), so an oversized upload is refused before it fills the disk. A
request is all or nothing: on any error every pending write is aborted, and the
caller commits the writes only once it has checked the scene in the database.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import anyio
from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect, Request

from api.paths import UnsafePathError, clean_relpath
from api.problems import ApiError, FieldError
from api.service.store import ArtifactStore, PendingWrite

MULTIPART_OVERHEAD = 64 * 1024  # headers and boundaries allowed on top of the file bytes


@dataclass(frozen=True)
class Limits:
    """What one request may still add to a scene."""

    max_file_bytes: int
    max_total_bytes: int  # bytes left in the scene's budget
    max_files: int  # files left in the scene's budget
    max_path_length: int


@dataclass
class Staged:
    """A received file, written to staging, not yet visible under its key."""

    path: str
    pending: PendingWrite


@dataclass
class StagedSet:
    files: list[Staged] = field(default_factory=list)

    @property
    def total_bytes(self) -> int:
        return sum(f.pending.size for f in self.files)

    def abort(self) -> None:
        for f in self.files:
            f.pending.abort()
        self.files.clear()


def too_large(detail: str) -> ApiError:
    return ApiError(413, "too-large", detail)


def check_content_length(request: Request, limit: int) -> None:
    """413 before reading a byte when the declared length is over ``limit``."""
    raw = request.headers.get("content-length")
    if raw is None:
        return
    try:
        n = int(raw)
    except ValueError:
        raise ApiError(400, "bad-request", "Content-Length is not a number") from None
    if n > limit:
        raise too_large(f"request body of {n} bytes is over the limit of {limit} bytes")


def _decode_header(raw: bytes) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


class _PartMachine:
    """Receives parser events (in order) and turns them into staged store writes."""

    def __init__(self, store: ArtifactStore, key_for: Callable[[str], str], limits: Limits) -> None:
        self.store = store
        self.key_for = key_for
        self.limits = limits
        self.staged = StagedSet()
        self.current: Staged | None = None
        self.seen: set[str] = set()
        self.ended = False

    # parser callbacks only record events; :meth:`apply` does the work off the loop
    def apply(self, events: list[tuple[str, Any]]) -> None:
        for kind, payload in events:
            if kind == "part":
                self._begin(payload)
            elif kind == "data":
                self._data(payload)
            elif kind == "end_part":
                if self.current is not None:  # its last bytes go out now, not at commit:
                    self.current.pending.seal()  # a request of many files holds one part
                self.current = None
            elif kind == "end":
                self.ended = True

    def _begin(self, headers: dict[str, str]) -> None:
        disposition = headers.get("content-disposition", "")
        kind, options = parse_options_header(disposition)
        if kind != b"form-data":
            raise ApiError(400, "bad-multipart", "a part has no 'form-data' Content-Disposition")
        raw_name = options.get(b"filename")
        field_name = _decode_header(options.get(b"name", b""))
        if raw_name is None:
            raise ApiError(
                422,
                "not-a-file",
                f"form field '{field_name}' is not a file: every part must carry a filename "
                "(its path inside the scene, e.g. 'train/r_0.png')",
                errors=[FieldError(field=f"body.{field_name}", message="expected a file part")],
            )
        name = _decode_header(raw_name)
        try:
            path = clean_relpath(name, self.limits.max_path_length)
        except UnsafePathError as exc:
            raise ApiError(
                422,
                "unsafe-path",
                f"file name '{name}' is not allowed: {exc}",
                errors=[FieldError(field=f"body.{field_name}.filename", message=str(exc))],
            ) from None
        if path in self.seen:
            raise ApiError(422, "duplicate-file", f"file '{path}' appears twice in the request")
        if len(self.staged.files) + 1 > self.limits.max_files:
            raise too_large(
                f"too many files: the scene may hold {self.limits.max_files} more at most"
            )
        self.seen.add(path)
        self.current = Staged(path, self.store.begin(self.key_for(path)))
        self.staged.files.append(self.current)

    def _data(self, data: bytes) -> None:
        cur = self.current
        if cur is None:
            return  # preamble bytes outside any part
        if cur.pending.size + len(data) > self.limits.max_file_bytes:
            raise too_large(
                f"file '{cur.path}' is over the limit of {self.limits.max_file_bytes} bytes"
            )
        if self.staged.total_bytes + len(data) > self.limits.max_total_bytes:
            raise too_large(
                f"upload would take the scene over its limit "
                f"({self.limits.max_total_bytes} more bytes allowed)"
            )
        cur.pending.write(data)


async def receive_multipart(
    request: Request,
    store: ArtifactStore,
    key_for: Callable[[str], str],
    limits: Limits,
    chunk_bytes: int = 1 << 20,
) -> StagedSet:
    """Stream a multipart/form-data body into staged writes, one per file part."""
    ctype, options = parse_options_header(request.headers.get("content-type"))
    if ctype != b"multipart/form-data":
        raise ApiError(
            415,
            "unsupported-media-type",
            f"expected multipart/form-data, got '{ctype.decode('latin-1') or 'nothing'}'",
        )
    boundary = options.get(b"boundary")
    if not boundary:
        raise ApiError(400, "bad-multipart", "multipart/form-data without a boundary")
    check_content_length(request, limits.max_total_bytes + MULTIPART_OVERHEAD * 16)

    machine = _PartMachine(store, key_for, limits)
    events: list[tuple[str, Any]] = []
    header_field: list[bytes] = []
    header_value: list[bytes] = []
    headers: dict[str, str] = {}

    def on_part_begin() -> None:
        headers.clear()

    def on_header_field(data: bytes, start: int, end: int) -> None:
        header_field.append(data[start:end])

    def on_header_value(data: bytes, start: int, end: int) -> None:
        header_value.append(data[start:end])

    def on_header_end() -> None:
        headers[b"".join(header_field).decode("latin-1").lower()] = b"".join(header_value).decode(
            "latin-1"
        )
        header_field.clear()
        header_value.clear()

    def on_headers_finished() -> None:
        events.append(("part", dict(headers)))

    def on_part_data(data: bytes, start: int, end: int) -> None:
        events.append(("data", bytes(data[start:end])))

    def on_part_end() -> None:
        events.append(("end_part", None))

    def on_end() -> None:
        events.append(("end", None))

    parser = MultipartParser(
        boundary,
        {
            "on_part_begin": on_part_begin,
            "on_header_field": on_header_field,
            "on_header_value": on_header_value,
            "on_header_end": on_header_end,
            "on_headers_finished": on_headers_finished,
            "on_part_data": on_part_data,
            "on_part_end": on_part_end,
            "on_end": on_end,
        },
        max_header_size=16 * 1024,
    )
    received = pending_bytes = 0

    async def apply_events() -> None:
        # batched so a thread hop moves about ``chunk_bytes``, not one network read
        nonlocal pending_bytes
        if events:
            batch = events[:]
            events.clear()
            await anyio.to_thread.run_sync(machine.apply, batch)
        pending_bytes = 0

    body_limit = limits.max_total_bytes + MULTIPART_OVERHEAD * (limits.max_files + 1)
    try:
        async for chunk in request.stream():
            received += len(chunk)
            if received > body_limit:
                raise too_large(f"request body is over the limit of {body_limit} bytes")
            try:
                parser.write(chunk)
            except MultipartParseError as exc:
                raise ApiError(400, "bad-multipart", f"malformed multipart body: {exc}") from None
            pending_bytes += len(chunk)
            if events and pending_bytes >= chunk_bytes:
                await apply_events()
        await apply_events()
        if not machine.ended:
            raise ApiError(400, "bad-multipart", "multipart body ended before its final boundary")
        if not machine.staged.files:
            raise ApiError(422, "no-files", "the request carries no files")
    except BaseException as exc:
        await anyio.to_thread.run_sync(machine.staged.abort)
        if isinstance(exc, ClientDisconnect):
            raise ApiError(400, "client-disconnected", "client went away mid-upload") from None
        raise
    return machine.staged


async def receive_body(
    request: Request, store: ArtifactStore, key: str, limit: int, chunk_bytes: int
) -> PendingWrite:
    """Stream a raw request body into one staged write (not committed), at most ``limit``."""
    check_content_length(request, limit)
    pending = store.begin(key)
    buffer: list[bytes] = []
    buffered = 0
    try:
        async for chunk in request.stream():
            if pending.size + buffered + len(chunk) > limit:
                raise too_large(f"request body is over the limit of {limit} bytes")
            buffer.append(chunk)
            buffered += len(chunk)
            if buffered >= chunk_bytes:
                data = b"".join(buffer)
                buffer.clear()
                buffered = 0
                await anyio.to_thread.run_sync(pending.write, data)
        if buffer:
            await anyio.to_thread.run_sync(pending.write, b"".join(buffer))
    except BaseException as exc:
        await anyio.to_thread.run_sync(pending.abort)
        if isinstance(exc, ClientDisconnect):
            raise ApiError(400, "client-disconnected", "client went away mid-upload") from None
        raise
    return pending
