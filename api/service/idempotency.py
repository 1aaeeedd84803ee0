"""``Idempotency-Key`` on creating POSTs: a retry answers what the first request made.

A client whose ``POST /v1/jobs`` timed out cannot know whether the job exists. Sent
again with the same ``Idempotency-Key``, the request finds the record the first one
wrote (in the same transaction as the object it created) and answers that object
instead of making a second. The record holds the SHA-256 of the request's body as
parsed (so key order and whitespace do not matter): the same key with a different body
is refused, since answering the old object would hide the client's mistake. Two racing
first requests collide on the unique (owner, route, key) constraint; the loser rolls
back and answers the winner's object.
"""

from __future__ import annotations

import hashlib
import json
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from api.service.db import Database
from api.service.models import IdempotencyRecord

MAX_KEY_LENGTH = 255


class KeyReusedError(Exception):
    """The key was used on this route with another body."""


def body_digest(body: Any) -> str:
    """SHA-256 of a JSON-able body in canonical form (sorted keys, no spaces)."""
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode()).hexdigest()


def valid_key(key: str) -> bool:
    """1-255 printable ASCII characters (the header's value as clients send it)."""
    return 0 < len(key) <= MAX_KEY_LENGTH and all(32 <= ord(c) < 127 for c in key)


def find(session: Session, owner: str, route: str, key: str, digest: str) -> str | None:
    """The id the key already created on this route, None if it is new.

    Raises :class:`KeyReusedError` when it was used with another body.
    """
    row = session.scalar(
        select(IdempotencyRecord).where(
            IdempotencyRecord.owner == owner,
            IdempotencyRecord.route == route,
            IdempotencyRecord.key == key,
        )
    )
    if row is None:
        return None
    if row.request_sha256 != digest:
        raise KeyReusedError(route)
    return row.resource_id


def remember(
    session: Session, owner: str, route: str, key: str, digest: str, resource_id: str
) -> None:
    """Record what the key created; committed with the object itself by the caller."""
    session.add(
        IdempotencyRecord(
            owner=owner, route=route, key=key, request_sha256=digest, resource_id=resource_id
        )
    )


def forget_expired(database: Database, ttl_s: float) -> int:
    """Drop records older than ``ttl_s``; how many went."""
    cutoff = datetime.now(UTC) - timedelta(seconds=ttl_s)
    with database.write() as s:
        result = s.execute(delete(IdempotencyRecord).where(IdempotencyRecord.created_at < cutoff))
    return int(getattr(result, "rowcount", 0) or 0)
