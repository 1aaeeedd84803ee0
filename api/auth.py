"""API keys: high-entropy random tokens, shown once, stored as SHA-256.

A key has 256 bits of randomness, so a plain (unsalted, fast) hash is enough: there
is nothing to brute-force, and lookup by hash stays one indexed query per request.
"""

from __future__ import annotations

import hashlib
import secrets
import threading
import time
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from api.service.models import ApiKey, new_id

KEY_PREFIX = "glk_"


@dataclass(frozen=True)
class Principal:
    """Who is calling: the owner their resources belong to, and the key used."""

    owner: str
    key_id: str


def hash_key(key: str) -> str:
    return hashlib.sha256(key.encode("utf-8")).hexdigest()


def create_key(session: Session, owner: str, name: str | None = None) -> tuple[ApiKey, str]:
    """A new key row for ``owner`` and the plaintext key (the only time it exists)."""
    key = KEY_PREFIX + secrets.token_urlsafe(32)
    row = ApiKey(
        id=new_id("key"),
        owner=owner,
        name=name or owner,
        key_hash=hash_key(key),
        prefix=key[: len(KEY_PREFIX) + 6],
    )
    session.add(row)
    session.flush()
    return row, key


def lookup(session: Session, key: str) -> Principal | None:
    """The principal of a live key, or None (unknown or revoked)."""
    if not key.startswith(KEY_PREFIX) or len(key) > 200:
        return None
    row = session.scalar(select(ApiKey).where(ApiKey.key_hash == hash_key(key)))
    if row is None or row.revoked_at is not None:
        return None
    return Principal(owner=row.owner, key_id=row.id)


class PrincipalCache:
    """Recently seen keys → principal, for ``ttl_s`` seconds (0 disables).

    Saves a database round trip per request for clients that poll. A revocation made
    through this process takes effect at once (:meth:`forget`); one made through
    another replica within ``ttl_s``.
    """

    def __init__(self, ttl_s: float, max_entries: int = 10_000) -> None:
        self.ttl_s = ttl_s
        self.max_entries = max_entries
        self._entries: dict[str, tuple[Principal, float]] = {}
        self._lock = threading.Lock()

    def get(self, key_hash: str) -> Principal | None:
        with self._lock:
            hit = self._entries.get(key_hash)
            if hit is None or hit[1] < time.monotonic():
                self._entries.pop(key_hash, None)
                return None
            return hit[0]

    def put(self, key_hash: str, principal: Principal) -> None:
        if self.ttl_s <= 0:
            return
        with self._lock:
            if len(self._entries) >= self.max_entries:
                self._entries.clear()
            self._entries[key_hash] = (principal, time.monotonic() + self.ttl_s)

    def forget(self, key_id: str) -> None:
        with self._lock:
            for h in [h for h, (p, _) in self._entries.items() if p.key_id == key_id]:
                del self._entries[h]
