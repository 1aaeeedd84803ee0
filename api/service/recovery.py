"""Putting lost jobs back on the queue: what a crashed runner or a lost message left.

Jobs are claimed in the database (``api.service.runner.claim``), so every path back to
``queued`` is a conditional UPDATE: concurrent reapers race harmlessly and a runner
that turns out to be alive finds its lease gone and stops.

A runner that stops heartbeating (killed, crashed, its machine gone) is *dead*: after
``stale_after_s`` without a heartbeat the reaper counts the death on the job
(``runner_deaths``) and says so in the job's ``error`` while it waits in the queue::

    runner glint-cuda0@gpu1:4242 stopped heartbeating at 2026-11-29T10:15:03Z;
    requeued (attempt 2 of 3)

The next runner resumes it from its checkpoint. A job that lost ``max_attempts``
runners ends ``failed`` (``the runner died 3 times: last seen on worker ... at ...``);
one whose cancel was requested ends ``cancelled``. The embedded queue does the same for
the jobs its process left ``running`` when it starts again (:func:`requeue_orphans`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import or_, select, update

from api.service.broker import drop_unacked, pending_job_ids, unacked_deliveries
from api.service.db import Database
from api.service.models import Job, JobState
from api.service.settings import Settings
from api.service.webhooks import record_job_end

log = logging.getLogger("glint.recovery")


def _now() -> datetime:
    return datetime.now(UTC)


def _when(t: datetime | None) -> str:
    return t.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ") if t is not None else "an unknown time"


def requeued_note(worker: str | None, seen: datetime | None, attempt: int, of: int) -> str:
    """The ``error`` of a job put back in the queue because its runner died."""
    return (
        f"runner {worker or '(unknown)'} stopped heartbeating at {_when(seen)}; "
        f"requeued (attempt {attempt} of {of})"
    )


def died_error(deaths: int, worker: str | None, seen: datetime | None) -> str:
    """The ``error`` of a job failed because its runners kept dying."""
    times = "once" if deaths == 1 else f"{deaths} times"
    return f"the runner died {times}: last seen on worker {worker or '(unknown)'} at {_when(seen)}"


def cancelled_note(worker: str | None, seen: datetime | None) -> str:
    return (
        f"runner {worker or '(unknown)'} stopped heartbeating at {_when(seen)} while the "
        "job was being cancelled; its last checkpoint is kept"
    )


@dataclass
class Settled:
    """What became of the jobs whose runner died."""

    requeued: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    cancelled: list[str] = field(default_factory=list)


def settle_dead_runners(
    database: Database,
    settings: Settings,
    *,
    all_running: bool = False,
    job_id: str | None = None,
    runner: str | None = None,
) -> Settled:
    """``running`` jobs whose runner died: back to ``queued``, or ``failed`` at the limit.

    A runner is dead when its heartbeat is older than ``stale_after_s`` (or, with
    ``all_running``, whenever the job is ``running``: the embedded queue at start-up,
    when this process is the only runner). Each death is counted in ``runner_deaths``;
    the ``max_attempts``-th fails the job, and a job whose cancel was requested ends
    ``cancelled``. Clearing the lease fences the old runner off, should it be alive
    after all (a stall, a partition): its next write matches no row and it stops.

    ``job_id`` and ``runner`` (a prefix of the job's ``worker``) narrow it to one job of
    one runner known to be dead, whatever its heartbeat says: the local queue's child
    process that exited while holding it.
    """
    now = _now()
    lost = Job.state == JobState.RUNNING
    if job_id is not None:
        lost = lost & (Job.id == job_id)
    if runner is not None:
        lost = lost & Job.worker.startswith(runner, autoescape=True)
        all_running = True
    if not all_running:
        cutoff = now - timedelta(seconds=settings.stale_after_s)
        lost = lost & or_(Job.heartbeat_at < cutoff, Job.heartbeat_at.is_(None))
    cols = (Job.id, Job.lease, Job.worker, Job.heartbeat_at, Job.runner_deaths)
    out = Settled()
    with database.write() as s:
        for r in s.execute(select(*cols, Job.cancel_requested).where(lost)).all():
            deaths = r.runner_deaths + 1
            values: dict[str, Any] = {"runner_deaths": deaths}
            if r.cancel_requested:  # nobody wants it run again
                bucket = out.cancelled
                values.update(state=JobState.CANCELLED, finished_at=now)
                values.update(error=cancelled_note(r.worker, r.heartbeat_at))
            elif deaths >= settings.max_attempts:
                bucket = out.failed
                values.update(state=JobState.FAILED, finished_at=now)
                values.update(error=died_error(deaths, r.worker, r.heartbeat_at))
            else:
                bucket = out.requeued
                attempt = deaths + 1
                values.update(state=JobState.QUEUED)
                values.update(
                    error=requeued_note(r.worker, r.heartbeat_at, attempt, settings.max_attempts)
                )
            same_runner = Job.lease == r.lease if r.lease is not None else Job.lease.is_(None)
            res = s.execute(
                update(Job)
                .where(Job.id == r.id, same_runner, lost)
                .values(**values, lease=None, updated_at=now, version=Job.version + 1)
                .execution_options(synchronize_session=False)
            )
            if res.rowcount == 1:
                bucket.append(r.id)
                if bucket is not out.requeued:  # the job ended here: its webhook event
                    record_job_end(s, r.id)
    return out


def requeue_orphans(database: Database, settings: Settings) -> list[str]:
    """Embedded mode at start-up: jobs left ``running`` by a dead process lost their runner.

    Only right when this process is the only runner (the local queue). Each such job is
    settled like a stale one (:func:`settle_dead_runners`: requeued with the reason, or
    failed at ``max_attempts``); returns the ids of every queued job, to enqueue again.
    """
    settled = settle_dead_runners(database, settings, all_running=True)
    log_settled(settled)
    with database.read() as s:
        return list(
            s.scalars(select(Job.id).where(Job.state == JobState.QUEUED).order_by(Job.created_at))
        )


def lost_queued(database: Database, settings: Settings) -> list[str]:
    """``queued`` jobs older than the grace with no message in the broker; touched, so
    other reapers skip them for another grace period."""
    now = _now()
    cutoff = now - timedelta(seconds=settings.queued_grace_s)
    with database.read() as s:
        rows = s.execute(
            select(Job.id, Job.updated_at).where(
                Job.state == JobState.QUEUED, Job.updated_at < cutoff
            )
        ).all()
    if not rows:
        return []
    try:
        waiting = pending_job_ids(settings, [r.id for r in rows])
    except Exception:  # cannot look: re-send all (duplicates are harmless)
        log.warning("reaper: cannot inspect the broker queue", exc_info=True)
        waiting = set()
    lost = []
    with database.write() as s:
        for r in rows:
            if r.id in waiting:
                continue
            res = s.execute(
                update(Job)
                .where(Job.id == r.id, Job.state == JobState.QUEUED, Job.updated_at == r.updated_at)
                .values(updated_at=now)
                .execution_options(synchronize_session=False)
            )
            if res.rowcount == 1:
                lost.append(r.id)
    return lost


def orphaned_deliveries(database: Database, settings: Settings, requeued: list[str]) -> list[str]:
    """Delivery tags in the broker's ``unacked`` hash that no live runner holds.

    A message stays unacknowledged while its job runs (``task_acks_late``); a worker
    killed mid-job never acknowledges it, and Redis would hand it out again only after
    the visibility timeout (a day). A delivery is orphaned when its job was just
    requeued (its runner is dead), or when its job is not ``running`` (finished,
    queued, deleted) and the delivery is older than ``stale_after_s``: a live runner
    claims its job within moments of receiving it. Dropping a delivery a live worker
    still holds costs nothing: its acknowledgement finds nothing to remove.
    """
    held = [(tag, job, since) for tag, job, since in unacked_deliveries(settings) if job]
    if not held:
        return []
    with database.read() as s:
        ids = {job for _, job, _ in held}
        states = {
            r.id: r.state for r in s.execute(select(Job.id, Job.state).where(Job.id.in_(ids)))
        }
    old = time.time() - settings.stale_after_s
    gone = set(requeued)
    return [
        tag
        for tag, job, since in held
        if job in gone or (states.get(job) != JobState.RUNNING and since < old)
    ]


@dataclass
class Reaped(Settled):
    """One reaper pass: settled dead runners, re-sent lost messages, dropped deliveries."""

    resent: list[str] = field(default_factory=list)  # queued jobs the broker had lost
    dropped: int = 0  # orphaned deliveries removed from Redis's ``unacked`` hash


def reap(database: Database, settings: Settings, send: Callable[[str], None]) -> Reaped:
    """One pass of the reaper (Celery queue): settle dead runners, clean the broker, re-send.

    Orphaned deliveries go before the new messages are sent, so a fresh delivery of a
    requeued job is never taken for its dead runner's.
    """
    settled = settle_dead_runners(database, settings)
    out = Reaped(settled.requeued, settled.failed, settled.cancelled)
    out.resent = lost_queued(database, settings)
    try:
        out.dropped = drop_unacked(
            settings, orphaned_deliveries(database, settings, settled.requeued)
        )
    except Exception:  # Redis down: the next pass tries again
        log.warning("reaper: cannot clean the broker's unacked deliveries", exc_info=True)
    for job_id in out.requeued + out.resent:
        try:
            send(job_id)
        except Exception:  # a queued job without a message: re-sent after queued_grace_s
            log.warning("job %s: cannot send it to the broker", job_id, exc_info=True)
    log_settled(out)
    for job_id in out.resent:
        log.warning("job %s: queued but not in the broker; re-sent", job_id)
    if out.dropped:
        log.warning("reaper: dropped %d orphaned unacked deliveries", out.dropped)
    return out


def log_settled(settled: Settled) -> None:
    for job_id in settled.requeued:
        log.warning("job %s: runner stopped heartbeating; re-queued to resume elsewhere", job_id)
    for job_id in settled.failed:
        log.warning("job %s: its runners kept dying; failed", job_id)
    for job_id in settled.cancelled:
        log.warning("job %s: runner died while cancelling; cancelled", job_id)


class Reaper:
    """The reaper on a thread of its own: the API runs one with the Celery queue, so a
    job whose only worker died is requeued even while no worker is alive to notice."""

    def __init__(self, database: Database, settings: Settings, send: Callable[[str], None]):
        self.database, self.settings, self.send = database, settings, send
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="glint-reaper", daemon=True)

    def start(self) -> Reaper:
        self._thread.start()
        return self

    def _loop(self) -> None:
        while not self._closed.wait(self.settings.reaper_interval_s):
            try:
                reap(self.database, self.settings, self.send)
            except Exception:
                log.warning("reaper pass failed", exc_info=True)

    def close(self) -> None:
        self._closed.set()
        if self._thread.is_alive():
            self._thread.join(10)
