"""Webhooks: a job's end becomes a signed JSON event, recorded for delivery.

Every place that writes a job's terminal state (the runner, the reaper, a cancel of a
queued job) calls :func:`record_job_end` in that same transaction: the delivery row
exists exactly when the end does, once per end (a resumed job that ends again gets
another). Sending is the dispatcher's job (:mod:`api.service.webhook_dispatch`), on a
thread of the API, so a slow or dead receiver never holds a job up.

Each request carries ``Glint-Signature: t=<unix seconds>,v1=<hex>``, where ``<hex>`` is
HMAC-SHA256 with the webhook's secret over ``f"{t}."`` followed by the raw body: the
receiver checks it with :func:`verify_signature` (standard library only, copy it), and
the timestamp bounds how long a captured request can be replayed.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import secrets
import threading
import time
import weakref
from datetime import UTC, datetime
from typing import Any

from pydantic_core import to_jsonable_python
from sqlalchemy import event
from sqlalchemy.orm import Session

from api.service.job_document import job_document
from api.service.models import DeliveryState, Job, JobState, WebhookDelivery, new_id

SECRET_PREFIX = "whsec_"
SIGNATURE_HEADER = "Glint-Signature"
EVENTS = {
    JobState.SUCCEEDED: "job.succeeded",
    JobState.FAILED: "job.failed",
    JobState.CANCELLED: "job.cancelled",
}


def new_secret() -> str:
    """A signing secret for a webhook that was given none: ``whsec_`` + 32 hex digits."""
    return SECRET_PREFIX + secrets.token_hex(16)


def signature(secret: str, timestamp: int, body: bytes) -> str:
    """Hex HMAC-SHA256 of ``f"{timestamp}."`` + ``body`` with ``secret``."""
    message = f"{timestamp}.".encode() + body
    return hmac.new(secret.encode("utf-8"), message, hashlib.sha256).hexdigest()


def signature_header(secret: str, body: bytes, timestamp: int | None = None) -> str:
    """The ``Glint-Signature`` value for ``body`` sent now (or at ``timestamp``)."""
    t = int(time.time()) if timestamp is None else timestamp
    return f"t={t},v1={signature(secret, t, body)}"


def verify_signature(
    secret: str, header: str, body: bytes, tolerance_s: float = 300, now: float | None = None
) -> bool:
    """Whether ``header`` (a ``Glint-Signature`` value) signs ``body`` with ``secret``, made
    within ``tolerance_s`` of now. ``body`` is the raw request body, before any parsing."""
    fields: dict[str, list[str]] = {}
    for part in header.split(","):
        name, _, value = part.strip().partition("=")
        fields.setdefault(name, []).append(value)
    try:
        t = int(fields["t"][0])
    except (KeyError, ValueError):
        return False
    if abs((time.time() if now is None else now) - t) > tolerance_s:
        return False
    expected = signature(secret, t, body)
    return any(hmac.compare_digest(expected, v) for v in fields.get("v1", []))


def record_job_end(session: Session, job: Job | str) -> WebhookDelivery | None:
    """Add the delivery of the job's end to ``session``'s transaction, which writes (or
    just wrote) its terminal state; None when the job has no webhook or has not ended.

    The body is built now, from the job as it ended: ``{"id", "event", "created_at",
    "job"}`` with the job as ``GET /v1/jobs/{id}`` shows it.
    """
    if isinstance(job, str):
        found = session.get(Job, job, populate_existing=True)
        if found is None:
            return None
        job = found
    event_name = EVENTS.get(job.state)
    if event_name is None or job.webhook_url is None:
        return None
    now = datetime.now(UTC)
    delivery_id = new_id("whd")
    payload = {
        "id": delivery_id,
        "event": event_name,
        "created_at": now,
        "job": job_document(job),
    }
    delivery = WebhookDelivery(
        id=delivery_id,
        owner=job.owner,
        url=job.webhook_url,
        event=event_name,
        payload=to_jsonable_python(payload),
        state=DeliveryState.PENDING,
        attempts=0,
        next_attempt_at=now,
        created_at=now,
    )
    job.webhook_deliveries.append(delivery)
    event.listen(session, "after_commit", _wake_after_commit, once=True)
    return delivery


def event_json(payload: dict[str, Any]) -> bytes:
    """The exact bytes sent (and signed) for a delivery's payload."""
    return json.dumps(payload, separators=(",", ":"), ensure_ascii=False).encode("utf-8")


# --- waking the dispatchers of this process ------------------------------------------

_waiters: weakref.WeakSet[threading.Event] = weakref.WeakSet()
_waiters_lock = threading.Lock()


def register_waiter(flag: threading.Event) -> None:
    """Have ``flag`` set whenever this process commits a job end with a webhook."""
    with _waiters_lock:
        _waiters.add(flag)


def wake_dispatchers() -> None:
    with _waiters_lock:
        flags = list(_waiters)
    for flag in flags:
        flag.set()


def _wake_after_commit(_session: Session) -> None:
    wake_dispatchers()
