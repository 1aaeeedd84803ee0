"""Request dependencies: settings, database session, store, queue, the caller.

Everything a route needs is injected from here, built once by the app factory and
kept on ``app.state``; tests swap any of them by building the app with others.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from typing import Annotated

import anyio
from fastapi import Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from api import auth
from api.problems import ApiError, FieldError
from api.service.db import Database
from api.service.queue import JobQueue
from api.service.settings import Settings
from api.service.store import ArtifactStore, LocalStore, StoreProbe

_bearer = HTTPBearer(auto_error=False, description="an API key from `glint keys create`")
CredentialsDep = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
SCOPE_EXTRA = "x-glint-scope"  # openapi_extra key: the scope a route needs (see required_scope)
_SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
log = logging.getLogger("glint.api")
_CLEANUP = anyio.CapacityLimiter(16)  # session cleanups never wait behind route threads
READ_THREADS = 4  # threads for the reads on every request's path (see read_threads)


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_database(request: Request) -> Database:
    return request.app.state.database


def get_store(request: Request) -> ArtifactStore:
    return request.app.state.store


def get_scratch(request: Request) -> LocalStore:
    """Where archives are spooled before unpacking (the store itself when it is a folder)."""
    return request.app.state.scratch


def get_queue(request: Request) -> JobQueue:
    return request.app.state.queue


def require_store(request: Request) -> None:
    """503 ``store-unavailable`` (within the probe's timeout) unless the store answers:
    nothing is created for work that could not read or write its files."""
    probe: StoreProbe = request.app.state.store_probe
    probe.require()


async def get_db(request: Request) -> AsyncIterator[Session]:
    """A session per request; unsafe methods get a write transaction.

    Routes that change state commit themselves before answering (a failed commit is
    an error, not a silently lost write); anything left uncommitted is rolled back.

    This dependency is async on purpose: its cleanup must not wait for a worker
    thread of the pool the sync routes run on, or a burst of requests could hold every
    database connection while their cleanups queue behind routes that are waiting for
    a connection. Opening a session does no I/O (the connection is taken at the first
    query, in the route's thread); closing runs on a limiter of its own.
    """
    database: Database = request.app.state.database
    unsafe = request.method not in _SAFE_METHODS
    session = database.write_sessions() if unsafe else database.sessions()
    try:
        yield session
    finally:  # rolls back whatever the route left uncommitted
        if unsafe:
            await anyio.to_thread.run_sync(session.close, limiter=_CLEANUP)
        else:
            session.close()  # ends a read transaction: no writes, no waiting on locks


def read_key(database: Database, key: str) -> auth.KeyRecord | None:
    """The key's record: one indexed read on a bare connection (no ORM session)."""
    with database.engine.connect() as connection:
        return auth.lookup(connection, key)


def _mark_used(database: Database, record: auth.KeyRecord, every_s: float) -> None:
    try:
        with database.write() as session:
            auth.touch(session, record.principal.key_id, every_s)
    except Exception:  # a busy database must not fail the request over a timestamp
        log.warning("could not record the use of key %s", record.principal.key_id)


async def note_use(request: Request, record: auth.KeyRecord) -> None:
    """Record the key's use when its last one is older than ``GLINT_KEY_LAST_USED_S``.

    A write, so it runs on the route threads (it may wait for SQLite's write lock), not
    on the read threads (:func:`read_threads`); it is due about once a minute per key.
    """
    every_s = request.app.state.settings.key_last_used_s
    if auth.due(record, every_s):
        await run_in_threadpool(_mark_used, request.app.state.database, record, every_s)


def read_threads(request: Request) -> anyio.CapacityLimiter:
    """The few threads that run the reads on every request's path (the caller's key, a
    job's status): short indexed reads that never wait for a lock.

    On the route threads (``GLINT_THREADS``, 40) they would run 40 at a time under load,
    each waiting for the GIL behind the others and behind the event loop; a handful at
    a time answers more requests, sooner (docs/api.md, *Latency under load*).
    """
    limiter: anyio.CapacityLimiter = request.app.state.read_threads
    return limiter


def required_scope(request: Request) -> str:
    """The scope a route needs: its ``x-glint-scope``, else ``read`` for GET/HEAD/OPTIONS
    and ``write`` for every other method (a new route that changes state is guarded
    without saying so)."""
    route = request.scope.get("route")
    declared = (getattr(route, "openapi_extra", None) or {}).get(SCOPE_EXTRA)
    if declared:
        return str(declared)
    return "read" if request.method in _SAFE_METHODS else "write"


_CHALLENGE = {"WWW-Authenticate": 'Bearer realm="glint"'}


def presented_key(credentials: HTTPAuthorizationCredentials | None) -> str:
    """The key of ``Authorization: Bearer <key>``; 401 when there is none."""
    if credentials is None:
        raise _unauthorized("missing API key: send 'Authorization: Bearer <key>'", _CHALLENGE)
    return credentials.credentials


def authorize(request: Request, record: auth.KeyRecord | None) -> auth.Principal:
    """The caller of a looked-up key: 401 unless it is live, 403 unless its scope covers
    the route's."""
    if record is None:
        raise _unauthorized("invalid or revoked API key", _CHALLENGE)
    principal = record.principal
    needed = required_scope(request)
    if not auth.allows(principal.scope, needed):
        raise forbidden(principal, needed, f"{request.method} {request.url.path}")
    return principal


async def get_principal(request: Request, credentials: CredentialsDep) -> auth.Principal:
    """The caller, from ``Authorization: Bearer <key>``, checked against the route's scope.

    Every request looks its key up: a revoked key fails at once, on every replica.
    """
    key = presented_key(credentials)
    database: Database = request.app.state.database
    record = await anyio.to_thread.run_sync(read_key, database, key, limiter=read_threads(request))
    if record is not None:
        await note_use(request, record)
    return authorize(request, record)


def _unauthorized(detail: str, headers: dict[str, str]) -> ApiError:
    return ApiError(
        401,
        "unauthorized",
        detail,
        errors=[FieldError(field="header.authorization", message=detail)],
        headers=headers,
    )


def forbidden(principal: auth.Principal, needed: str, what: str) -> ApiError:
    """403: the key is valid, its scope too narrow for ``what``."""
    message = f"needs a key with scope '{needed}'; this key's scope is '{principal.scope}'"
    return ApiError(
        403,
        "insufficient-scope",
        f"{what} {message}",
        errors=[FieldError(field="header.authorization", message=message)],
    )


async def require_json(
    request: Request, _caller: Annotated[auth.Principal, Depends(get_principal)]
) -> None:
    """415 unless the body is declared JSON (FastAPI would otherwise guess); after auth."""
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype != "application/json" and not ctype.endswith("+json"):
        raise ApiError(
            415,
            "unsupported-media-type",
            f"expected an application/json body, got '{ctype or 'no content type'}'",
        )


JsonBody = Depends(require_json)
SettingsDep = Annotated[Settings, Depends(get_settings)]
DatabaseDep = Annotated[Database, Depends(get_database)]
SessionDep = Annotated[Session, Depends(get_db)]
StoreDep = Annotated[ArtifactStore, Depends(get_store)]
ScratchDep = Annotated[LocalStore, Depends(get_scratch)]
StoreUp = Depends(require_store)
QueueDep = Annotated[JobQueue, Depends(get_queue)]
PrincipalDep = Annotated[auth.Principal, Depends(get_principal)]
