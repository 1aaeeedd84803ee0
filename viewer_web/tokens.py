"""Short-lived viewer tokens: an HMAC over (job, owner, expiry).

Why not the API key itself: the page would have to keep it in memory, in URLs of
WebSocket and image requests, and in server logs. A viewer token grants only "view
this one job" for a few minutes, so a leaked one is worth little. Tokens are
stateless (nothing to store or clean up); replicas given the same secret (the API's
``GLINT_VIEWER_SECRET`` setting) accept each other's tokens, otherwise each process
signs with its own random key.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import secrets
import time
from dataclasses import dataclass

TOKEN_PREFIX = "gvt_"
DEFAULT_TTL_S = 15 * 60


def default_secret() -> bytes:
    """A per-process key, for services not given a shared secret."""
    return secrets.token_bytes(32)


@dataclass(frozen=True)
class ViewerGrant:
    """What a valid token allows: viewing ``job_id`` on behalf of ``owner`` until ``expires``."""

    job_id: str
    owner: str
    expires: float


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode("ascii")


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def issue(secret: bytes, job_id: str, owner: str, ttl_s: float = DEFAULT_TTL_S) -> ViewerGrant:
    """A grant for ``job_id`` valid for ``ttl_s`` seconds; :func:`encode` makes the token."""
    return ViewerGrant(job_id, owner, time.time() + ttl_s)


def encode(secret: bytes, grant: ViewerGrant) -> str:
    """The signed token text of ``grant``."""
    body = _b64(
        json.dumps(
            {"j": grant.job_id, "o": grant.owner, "e": int(grant.expires)}, separators=(",", ":")
        ).encode("utf-8")
    )
    sig = _b64(hmac.new(secret, body.encode("ascii"), hashlib.sha256).digest())
    return f"{TOKEN_PREFIX}{body}.{sig}"


def verify(secret: bytes, token: str | None, job_id: str) -> ViewerGrant | None:
    """The grant of a genuine, unexpired token for ``job_id``, else None (never raises)."""
    if not token or not token.startswith(TOKEN_PREFIX) or len(token) > 1024:
        return None
    try:
        body, sig = token[len(TOKEN_PREFIX) :].split(".", 1)
        want = hmac.new(secret, body.encode("ascii"), hashlib.sha256).digest()
        if not hmac.compare_digest(want, _unb64(sig)):
            return None
        data = json.loads(_unb64(body))
        grant = ViewerGrant(str(data["j"]), str(data["o"]), float(data["e"]))
    except (ValueError, KeyError, TypeError, UnicodeError):
        return None
    if grant.job_id != job_id or grant.expires < time.time():
        return None
    return grant
