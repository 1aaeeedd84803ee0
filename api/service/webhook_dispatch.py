"""The webhook dispatcher: sends due deliveries from a thread of the API, with retries.

Deliveries are rows (:class:`~api.service.models.WebhookDelivery`) written with the
job's end, wherever the job ended (a worker, the API's runner, the reaper); every API
process runs one :class:`Dispatcher`, which polls for deliveries whose
``next_attempt_at`` has passed (and is woken at once when its own process records one).
Each attempt is claimed with a conditional ``UPDATE`` (``attempts`` as it was read,
``next_attempt_at`` moved past the attempt's longest duration), so replicas never send
one attempt twice, and an attempt cut off by a crash is tried again after that lease.

An attempt answers 2xx: ``delivered``. Anything else (another status, a timeout, a
refused connection) is tried again after ``webhook_backoff_s * 2**(attempts - 1)``
seconds (at most ``webhook_backoff_max_s``) until ``webhook_max_attempts``, then the
delivery is ``failed`` with the last error. A host that is, or resolves to, a forbidden
address (:mod:`api.service.webhook_guard`) fails the delivery at once; redirects are
not followed, and proxies from the environment are not used.
"""

from __future__ import annotations

import logging
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

import httpx
from sqlalchemy import select, update

from api.service.db import Database
from api.service.models import DeliveryState, Job, WebhookDelivery
from api.service.settings import Settings
from api.service.webhook_guard import (
    ForbiddenAddressError,
    UnresolvableHostError,
    resolve_public,
    split_url,
)
from api.service.webhooks import SIGNATURE_HEADER, event_json, register_waiter, signature_header

log = logging.getLogger("glint.webhooks")

CONCURRENCY = 4  # deliveries sent at once by one dispatcher (a slow receiver holds one)
ERROR_MAX_CHARS = 1000


def _now() -> datetime:
    return datetime.now(UTC)


@dataclass(frozen=True)
class Claimed:
    """One attempt of one delivery, claimed by this process."""

    id: str
    job_id: str
    url: str
    event: str
    payload: dict[str, Any]
    secret: str
    attempts: int  # counting this one


@dataclass(frozen=True)
class Outcome:
    status: int | None = None  # the receiver's HTTP status, if it answered
    error: str | None = None  # why the attempt failed; None: delivered
    final: bool = False  # no point trying again (a forbidden address)


def backoff_s(settings: Settings, attempts: int) -> float:
    """Seconds before the next attempt after ``attempts`` failed ones."""
    return min(
        settings.webhook_backoff_s * 2 ** max(attempts - 1, 0), settings.webhook_backoff_max_s
    )


def lease_s(settings: Settings) -> float:
    """How long a claimed attempt may take (resolve, connect, send, read) before another
    dispatcher may take it for lost."""
    return 4 * settings.webhook_timeout_s + 30.0


def due(database: Database, limit: int) -> list[tuple[str, int]]:
    """(id, attempts) of pending deliveries whose next attempt is due, oldest first."""
    with database.read() as s:
        rows = s.execute(
            select(WebhookDelivery.id, WebhookDelivery.attempts)
            .where(
                WebhookDelivery.state == DeliveryState.PENDING,
                WebhookDelivery.next_attempt_at <= _now(),
            )
            .order_by(WebhookDelivery.next_attempt_at)
            .limit(limit)
        ).all()
    return [(r.id, r.attempts) for r in rows]


def claim(database: Database, settings: Settings, delivery_id: str, seen: int) -> Claimed | None:
    """Take the next attempt of a due delivery; None when another dispatcher has it."""
    now = _now()
    with database.write() as s:
        res = s.execute(
            update(WebhookDelivery)
            .where(
                WebhookDelivery.id == delivery_id,
                WebhookDelivery.state == DeliveryState.PENDING,
                WebhookDelivery.attempts == seen,
                WebhookDelivery.next_attempt_at <= now,
            )
            .values(attempts=seen + 1, next_attempt_at=now + timedelta(seconds=lease_s(settings)))
            .execution_options(synchronize_session=False)
        )
        if res.rowcount != 1:
            return None
        row = s.execute(
            select(WebhookDelivery, Job.webhook_secret)
            .join(Job, Job.id == WebhookDelivery.job_id)
            .where(WebhookDelivery.id == delivery_id)
        ).one()
        d, secret = row
        return Claimed(d.id, d.job_id, d.url, d.event, d.payload, secret or "", seen + 1)


def send(client: httpx.Client, claimed: Claimed, settings: Settings) -> Outcome:
    """One attempt: POST the signed event to the address the host was checked at."""
    try:
        parts = split_url(claimed.url)
        https = parts.scheme.lower() == "https"
        host = parts.hostname or ""
        port = parts.port or (443 if https else 80)
        ip = resolve_public(host, port, allow_private=settings.webhook_allow_private)
    except ForbiddenAddressError as exc:
        return Outcome(
            error=f"refused: {exc}; webhooks go to public addresses only "
            "(GLINT_WEBHOOK_ALLOW_PRIVATE)",
            final=True,
        )
    except UnresolvableHostError as exc:
        return Outcome(error=str(exc))
    except ValueError as exc:  # a URL stored before the checks it fails (cannot improve)
        return Outcome(error=f"bad URL: {exc}", final=True)
    body = event_json(claimed.payload)
    from core import __version__

    headers = {
        "Content-Type": "application/json",
        "User-Agent": f"Glint-Webhooks/{__version__}",
        "Glint-Event": claimed.event,
        "Glint-Delivery": claimed.id,
        SIGNATURE_HEADER: signature_header(claimed.secret, body),
        "Host": parts.netloc.rpartition("@")[2],
    }
    # connect to the address that was checked, not to whatever the name resolves to next
    target = httpx.URL(claimed.url).copy_with(host=str(ip))
    extensions = {"sni_hostname": host} if https else {}
    try:
        with client.stream(
            "POST", target, content=body, headers=headers, extensions=extensions
        ) as r:
            status = r.status_code  # the body is not read: nothing in it matters
    except httpx.TimeoutException:
        return Outcome(error=f"no answer within {settings.webhook_timeout_s:g} s")
    except httpx.HTTPError as exc:
        return Outcome(error=f"{type(exc).__name__}: {exc}"[:ERROR_MAX_CHARS])
    if 200 <= status < 300:
        return Outcome(status=status)
    if 300 <= status < 400:
        where = r.headers.get("location", "")[:200]
        return Outcome(status, f"answered {status} (to {where}); redirects are not followed")
    return Outcome(status, f"answered {status}")


def record(
    database: Database, settings: Settings, claimed: Claimed, outcome: Outcome
) -> str | None:
    """Write an attempt's outcome; the delivery's state after it, or None when the attempt
    was no longer this dispatcher's (it outlived its lease and another one took over)."""
    now = _now()
    values: dict[str, Any] = {"last_status": outcome.status, "last_error": outcome.error}
    if outcome.error is None:
        state = DeliveryState.DELIVERED
        values.update(delivered_at=now, next_attempt_at=None)
    elif outcome.final or claimed.attempts >= settings.webhook_max_attempts:
        state = DeliveryState.FAILED
        values.update(next_attempt_at=None)
    else:
        state = DeliveryState.PENDING
        wait = timedelta(seconds=backoff_s(settings, claimed.attempts))
        values.update(next_attempt_at=now + wait)
    with database.write() as s:
        res = s.execute(
            update(WebhookDelivery)
            .where(
                WebhookDelivery.id == claimed.id,
                WebhookDelivery.state == DeliveryState.PENDING,
                WebhookDelivery.attempts == claimed.attempts,
            )
            .values(state=state, **values)
            .execution_options(synchronize_session=False)
        )
        if res.rowcount != 1:
            return None
        # the job's representation changed: a new version (and ETag) for its readers
        s.execute(
            update(Job)
            .where(Job.id == claimed.job_id)
            .values(version=Job.version + 1)
            .execution_options(synchronize_session=False)
        )
    return state


def attempt(
    database: Database, settings: Settings, client: httpx.Client, claimed: Claimed
) -> str | None:
    """Send one claimed attempt and record it; the delivery's state after it."""
    outcome = send(client, claimed, settings)
    state = record(database, settings, claimed, outcome)
    how = "delivered" if outcome.error is None else f"attempt failed: {outcome.error}"
    level = logging.WARNING if state == DeliveryState.FAILED else logging.INFO
    log.log(
        level,
        "webhook %s (%s, job %s, attempt %d): %s; %s",
        claimed.id,
        claimed.event,
        claimed.job_id,
        claimed.attempts,
        how,
        state or "not recorded: another dispatcher took the attempt over",
    )
    return state


class Dispatcher:
    """Deliveries due, sent on a few threads; the API runs one beside its sweeper."""

    def __init__(self, database: Database, settings: Settings) -> None:
        self.database, self.settings = database, settings
        self.client = httpx.Client(
            timeout=settings.webhook_timeout_s, follow_redirects=False, trust_env=False
        )
        self._wake = threading.Event()
        self._closed = threading.Event()
        self._pool = ThreadPoolExecutor(CONCURRENCY, thread_name_prefix="glint-webhook")
        self._inflight: set[Future[str]] = set()
        self._thread = threading.Thread(target=self._loop, name="glint-webhooks", daemon=True)
        register_waiter(self._wake)

    def start(self) -> Dispatcher:
        self._thread.start()
        return self

    def _loop(self) -> None:
        while not self._closed.is_set():
            try:
                self.dispatch()
            except Exception:
                log.warning("webhook dispatch pass failed", exc_info=True)
            self._wake.wait(self.settings.webhook_poll_s)
            self._wake.clear()

    def dispatch(self) -> int:
        """Claim and start the due deliveries there are free threads for; how many."""
        self._inflight = {f for f in self._inflight if not f.done()}
        free = CONCURRENCY - len(self._inflight)
        started = 0
        for delivery_id, seen in due(self.database, free) if free > 0 else []:
            claimed = claim(self.database, self.settings, delivery_id, seen)
            if claimed is None or self._closed.is_set():
                continue
            future = self._pool.submit(attempt, self.database, self.settings, self.client, claimed)
            future.add_done_callback(lambda _f: self._wake.set())  # a thread is free again
            self._inflight.add(future)
            started += 1
        return started

    def close(self) -> None:
        self._closed.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(10)
        # attempts under way finish (within the timeout) and are recorded
        self._pool.shutdown(wait=True, cancel_futures=True)
        self.client.close()
