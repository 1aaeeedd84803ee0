"""Putting lost jobs back on the queue: what a crashed runner or a lost message left.

Jobs are claimed in the database (``api.service.runner.claim``), so every path back to
``queued`` is a conditional UPDATE: concurrent reapers race harmlessly and a runner
that turns out to be alive finds its lease gone and stops.
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime, timedelta

from sqlalchemy import or_, select, update

from api.service.broker import pending_job_ids
from api.service.db import Database
from api.service.models import Job, JobState
from api.service.settings import Settings

log = logging.getLogger("glint.recovery")


def _now() -> datetime:
    return datetime.now(UTC)


def requeue_orphans(database: Database) -> list[str]:
    """Embedded mode at start-up: jobs left ``running`` by a dead process go back to queued.

    Only right when this process is the only runner (the local queue); returns the ids
    of every queued job, to enqueue again.
    """
    now = _now()
    with database.write() as s:
        s.execute(
            update(Job)
            .where(Job.state == JobState.RUNNING)
            .values(state=JobState.QUEUED, lease=None, updated_at=now, version=Job.version + 1)
        )
        return list(
            s.scalars(select(Job.id).where(Job.state == JobState.QUEUED).order_by(Job.created_at))
        )


def requeue_stale_running(database: Database, stale_after_s: float) -> list[str]:
    """``running`` jobs without heartbeat for ``stale_after_s`` back to ``queued``; their ids.

    Clearing the lease fences the old runner off, should it be alive after all (a
    stall, a partition): its next write matches no row and it stops.
    """
    now = _now()
    cutoff = now - timedelta(seconds=stale_after_s)
    stale = (Job.state == JobState.RUNNING) & or_(
        Job.heartbeat_at < cutoff, Job.heartbeat_at.is_(None)
    )
    taken = []
    with database.write() as s:
        for job_id in s.scalars(select(Job.id).where(stale)).all():
            res = s.execute(
                update(Job)
                .where(Job.id == job_id, stale)
                .values(state=JobState.QUEUED, lease=None, updated_at=now, version=Job.version + 1)
                .execution_options(synchronize_session=False)
            )
            if res.rowcount == 1:
                taken.append(job_id)
    return taken


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
