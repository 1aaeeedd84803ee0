"""Request dependencies: settings, database session, store, queue, the caller.

Everything a route needs is injected from here, built once by the app factory and
kept on ``app.state``; tests swap any of them by building the app with others.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Annotated

import anyio
from fastapi import Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from api import auth
from api.problems import ApiError
from api.service.db import Database
from api.service.queue import JobQueue
from api.service.settings import Settings
from api.service.store import ArtifactStore

_bearer = HTTPBearer(auto_error=False, description="an API key from `glint keys create`")
_SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
_CLEANUP = anyio.CapacityLimiter(16)  # session cleanups never wait behind route threads


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_database(request: Request) -> Database:
    return request.app.state.database


def get_store(request: Request) -> ArtifactStore:
    return request.app.state.store


def get_queue(request: Request) -> JobQueue:
    return request.app.state.queue


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


def _lookup(database: Database, key: str) -> auth.Principal | None:
    with database.read() as session:
        return auth.lookup(session, key)


async def get_principal(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> auth.Principal:
    """The caller, from ``Authorization: Bearer <key>`` (cached briefly, see PrincipalCache)."""
    challenge = {"WWW-Authenticate": 'Bearer realm="glint"'}
    if credentials is None:
        raise ApiError(
            401,
            "unauthorized",
            "missing API key: send 'Authorization: Bearer <key>'",
            headers=challenge,
        )
    cache: auth.PrincipalCache = request.app.state.principals
    digest = auth.hash_key(credentials.credentials)
    principal = cache.get(digest)
    if principal is None:
        database: Database = request.app.state.database
        principal = await run_in_threadpool(_lookup, database, credentials.credentials)
        if principal is None:
            raise ApiError(401, "unauthorized", "invalid or revoked API key", headers=challenge)
        cache.put(digest, principal)
    return principal


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
QueueDep = Annotated[JobQueue, Depends(get_queue)]
PrincipalDep = Annotated[auth.Principal, Depends(get_principal)]
