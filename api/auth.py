"""API keys: high-entropy random tokens, shown once, stored as SHA-256, with a scope.

A key has 256 bits of randomness, so a plain (unsalted, fast) hash is enough: there
is nothing to brute-force, and lookup by hash stays one indexed query per request.
Every request looks its key up (no cache): a revoked key fails at once, on every
replica.

A key's scope is what it may do, each including the ones before it:

* ``read``: every ``GET`` (and a viewer token), nothing that changes anything;
* ``write``: also create, upload, commit, train, cancel, resume, delete;
* ``admin``: also create keys and revoke other keys of the owner.

Any key may revoke itself. Keys made on the command line (``glint keys create``) are
``admin`` unless told otherwise; keys from before scopes existed became ``admin``.
"""

from __future__ import annotations

import hashlib
import logging
import secrets
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

from sqlalchemy import Connection, bindparam, or_, select, update
from sqlalchemy.orm import Session

from api.service.models import ApiKey, new_id

KEY_PREFIX = "glk_"
SCOPES = ("read", "write", "admin")  # each includes the ones before it
log = logging.getLogger("glint.api")


@dataclass(frozen=True)
class Principal:
    """Who is calling: the owner their resources belong to, and the key used."""

    owner: str
    key_id: str
    scope: str = "admin"
    name: str = ""


def allows(scope: str, needed: str) -> bool:
    """Whether a key of ``scope`` may do what needs ``needed``."""
    return scope in SCOPES and SCOPES.index(scope) >= SCOPES.index(needed)


def hash_key(key: str) -> str:
    return hashlib.sha256(key.encode("utf-8")).hexdigest()


def create_key(
    session: Session, owner: str, name: str | None = None, scope: str = "admin"
) -> tuple[ApiKey, str]:
    """A new key row for ``owner`` and the plaintext key (the only time it exists)."""
    if scope not in SCOPES:
        raise ValueError(f"unknown scope {scope!r}; expected one of {', '.join(SCOPES)}")
    key = KEY_PREFIX + secrets.token_urlsafe(32)
    row = ApiKey(
        id=new_id("key"),
        owner=owner,
        name=name or owner,
        key_hash=hash_key(key),
        prefix=key[: len(KEY_PREFIX) + 6],
        scope=scope,
    )
    session.add(row)
    session.flush()
    return row, key


@dataclass(frozen=True)
class KeyRecord:
    """A live key as looked up: its principal, and when it was last marked used."""

    principal: Principal
    last_used_at: datetime | None


# Built once: every request runs it, and building a select costs more than running it.
_BY_HASH = select(
    ApiKey.owner,
    ApiKey.id,
    ApiKey.scope,
    ApiKey.name,
    ApiKey.last_used_at,
    ApiKey.revoked_at,
).where(ApiKey.key_hash == bindparam("key_hash"))


def lookup(db: Session | Connection, key: str) -> KeyRecord | None:
    """The live key ``key`` names, or None (malformed, unknown or revoked).

    One indexed read of plain columns (no ORM object): it runs on every request.
    """
    if not key.startswith(KEY_PREFIX) or len(key) > 200:
        return None
    row = db.execute(_BY_HASH, {"key_hash": hash_key(key)}).first()
    if row is None or row.revoked_at is not None:
        return None
    return KeyRecord(Principal(row.owner, row.id, row.scope, row.name), row.last_used_at)


def touch(session: Session, key_id: str, every_s: float) -> None:
    """Mark a key used now, unless it was marked within ``every_s`` (one conditional
    UPDATE: concurrent requests of one key write it once)."""
    now = datetime.now(UTC)
    q = update(ApiKey).where(ApiKey.id == key_id)
    if every_s > 0:
        stale = now - timedelta(seconds=every_s)
        q = q.where(or_(ApiKey.last_used_at.is_(None), ApiKey.last_used_at < stale))
    session.execute(q.values(last_used_at=now).execution_options(synchronize_session=False))


def due(record: KeyRecord, every_s: float) -> bool:
    """Whether ``record``'s last use is older than ``every_s`` (so worth writing)."""
    last = record.last_used_at
    return last is None or datetime.now(UTC) - last >= timedelta(seconds=every_s)
