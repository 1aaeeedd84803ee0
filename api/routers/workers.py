"""Workers: which training workers are alive, on what device, running which job.

Celery workers upsert a row in ``workers`` every few seconds with an ``expires_at``
of their own choosing; a row past it is a dead (or partitioned) worker and is not
listed. A worker's current job is shown only to that job's owner.
"""

from __future__ import annotations

from datetime import UTC, datetime

from fastapi import APIRouter
from sqlalchemy import select

from api.deps import PrincipalDep, SessionDep, SettingsDep
from api.pages import Limit, Offset, page_rows
from api.problems import responses
from api.schemas import Page, WorkerOut
from api.service.models import Job, Worker
from api.strict_json import StrictJsonRoute

router = APIRouter(prefix="/workers", tags=["workers"], route_class=StrictJsonRoute)


@router.get(
    "",
    response_model=Page[WorkerOut],
    responses=responses(401, 422),
    summary="Alive workers: device, current job, last heartbeat",
)
def list_workers(
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    limit: Limit = 50,
    offset: Offset = 0,
) -> Page[WorkerOut]:
    now = datetime.now(UTC)
    limit = min(limit, settings.page_size_max)
    query = (
        select(Worker, Job.owner)
        .outerjoin(Job, Job.id == Worker.current_job)
        .where(Worker.expires_at > now)
        .order_by(Worker.id)
    )
    rows, total = page_rows(session, query, limit, offset, scalars=False)
    items = [
        WorkerOut(
            id=w.id,
            host=w.host,
            pid=w.pid,
            device=w.device,
            busy=w.current_job is not None,
            current_job=w.current_job if owner == principal.owner else None,
            started_at=w.started_at,
            heartbeat_at=w.heartbeat_at,
        )
        for w, owner in rows
    ]
    return Page[WorkerOut](items=items, total=total, limit=limit, offset=offset)
