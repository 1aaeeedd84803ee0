"""Jobs: create on a ready scene, read (or follow as server-sent events), cancel, resume.

State machine (the database is the source of truth; the queue only delivers ids)::

    queued ──► running ──► succeeded | failed | cancelled
      │                                   │       │
      └────────── cancel ──► cancelled    └─ resume ─► queued

Cancelling a queued job is immediate; a running job gets ``cancel_requested`` and its
runner stops at the next check (saving a checkpoint). Resume re-queues a cancelled or
failed job, which continues from the run folder's checkpoint.
"""

from __future__ import annotations

import json
import logging
from collections.abc import AsyncIterator
from datetime import UTC, datetime
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Depends, Header, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from sqlalchemy import Row, bindparam, func, select
from sqlalchemy.orm import Session, selectinload

from api.auth import KeyRecord, Principal, lookup
from api.deps import (
    CredentialsDep,
    DatabaseDep,
    JsonBody,
    PrincipalDep,
    QueueDep,
    SessionDep,
    SettingsDep,
    StoreDep,
    StoreUp,
    authorize,
    note_use,
    presented_key,
    read_threads,
)
from api.idempotent import IdempotencyKey, commit_or_replay, replayed
from api.job_webhook import job_webhook, with_made_secret
from api.problems import ApiError, FieldError, not_found, responses
from api.routers.scenes import owned_scene
from api.schemas import JobCreate, JobKindName, JobOut, JobStateName, Page, SfmConfig
from api.service.db import Database
from api.service.discard import discard
from api.service.job_document import DELIVERIES_SHOWN, SUMMARY_FIELDS
from api.service.models import Job, JobState, Scene, SceneState, WebhookDelivery, new_id
from api.service.queue import JobQueue
from api.service.store import job_key
from api.service.webhooks import record_job_end
from api.strict_json import StrictJsonRoute
from api.views import job_out

router = APIRouter(prefix="/jobs", tags=["jobs"], route_class=StrictJsonRoute)
log = logging.getLogger("glint.api")

JobId = Annotated[str, Path(max_length=40, description="job id (job_...)")]
AUTH = (401, 404)
CREATE_ROUTE = "POST /v1/jobs"


def _now() -> datetime:
    return datetime.now(UTC)


def owned_job(session: Session, principal: Principal, job_id: str, *, lock: bool = False) -> Job:
    q = select(Job).where(Job.id == job_id, Job.owner == principal.owner)
    if lock:
        q = q.with_for_update()
    job = session.scalar(q)
    if job is None:
        raise not_found("job", job_id)
    return job


def _etag(job: Job | Row[Any]) -> str:
    return f'W/"{job.id}-{job.version}"'


def sfm_record(scene: Scene, options: SfmConfig | None) -> dict[str, Any] | None:
    """The job's ``sfm`` column: options for a scene of photos without poses (None for a
    scene with poses); options that cannot apply answer 422 naming the field."""
    report = scene.report or {}
    if not report.get("needs_sfm"):
        if options is not None:
            raise _sfm_refused(
                "body.sfm",
                f"scene '{scene.id}' has poses (format {scene.format}); structure-from-motion "
                "options apply only to scenes of photos without poses",
            )
        return None
    options = options or SfmConfig()
    if options.feature_masks and not report.get("masks"):
        raise _sfm_refused(
            "body.sfm.feature_masks", f"feature masks need masks; scene '{scene.id}' has none"
        )
    return {"options": options.model_dump(mode="json"), "result": None}


def _sfm_refused(field: str, message: str) -> ApiError:
    return ApiError(
        422, "validation-error", message, errors=[FieldError(field=field, message=message)]
    )


def enqueue(queue: JobQueue, job_id: str) -> None:
    try:
        queue.enqueue(job_id)
    except Exception as exc:
        log.exception("enqueue of job %s failed", job_id)
        raise ApiError(
            503,
            "queue-unavailable",
            f"job '{job_id}' is saved as queued but could not be handed to the queue "
            f"({type(exc).__name__}); resubmit with POST /v1/jobs/{job_id}/resume later",
        ) from None


@router.post(
    "",
    status_code=201,
    response_model=JobOut,
    responses=responses(400, *AUTH, 409, 415, 422, 503),
    dependencies=[JsonBody, StoreUp],
    summary="Create a training job on a ready scene",
    description="On a scene of photos without poses (`report.needs_sfm`) the job starts with "
    "an `sfm` phase that recovers the cameras; `sfm` holds its options (refused, 422, on a "
    "scene with poses).",
)
def create_job(
    body: JobCreate,
    principal: PrincipalDep,
    session: SessionDep,
    queue: QueueDep,
    settings: SettingsDep,
    response: Response,
    idempotency_key: IdempotencyKey = None,
) -> JobOut:
    request_body = body.model_dump(mode="json")
    existing = replayed(session, principal, CREATE_ROUTE, idempotency_key, request_body, response)
    if existing is not None:  # a retry: answer what the first request made
        return job_out(owned_job(session, principal, existing))
    hook = job_webhook(session, principal, body.webhook, settings)  # 422: forbidden address
    scene = owned_scene(session, principal, body.scene_id)
    if scene.state != SceneState.READY:
        raise ApiError(
            409,
            "scene-not-ready",
            f"scene '{scene.id}' is {scene.state}; commit it (and pass validation) first",
        )
    cfg = body.config
    job = Job(
        id=new_id("job"),
        owner=principal.owner,
        scene_id=scene.id,
        config=cfg.model_dump(mode="json"),
        total_iterations=cfg.iterations,
        sfm=sfm_record(scene, body.sfm),
        **hook.columns(),
    )
    session.add(job)
    session.flush()
    # the row exists before any runner can be handed its id
    existing = commit_or_replay(
        session, principal, CREATE_ROUTE, idempotency_key, request_body, job.id, response
    )
    if existing is not None:  # a request with the same key won the race
        return job_out(owned_job(session, principal, existing))
    enqueue(queue, job.id)
    return with_made_secret(job_out(job), hook)


@router.get("", response_model=Page[JobOut], responses=responses(401, 422), summary="List jobs")
def list_jobs(
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    state: Annotated[list[JobStateName] | None, Query(description="any of these states")] = None,
    scene_id: Annotated[str | None, Query(max_length=40)] = None,
    kind: Annotated[
        JobKindName | None, Query(description="only training jobs, or only mesh jobs")
    ] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    offset: Annotated[int, Query(ge=0, le=2**31)] = 0,
) -> Page[JobOut]:
    limit = min(limit, settings.page_size_max)
    where = [Job.owner == principal.owner]
    if state:
        where.append(Job.state.in_(state))
    if scene_id:
        where.append(Job.scene_id == scene_id)
    if kind:
        where.append(Job.kind == kind)
    return job_page(session, where, limit, offset)


def job_page(session: Session, where: list[Any], limit: int, offset: int) -> Page[JobOut]:
    """One page of the jobs matching ``where``, newest first, with the total count."""
    total = session.scalar(select(func.count()).select_from(Job).where(*where)) or 0
    rows = session.scalars(
        select(Job)
        .where(*where)
        .order_by(Job.created_at.desc(), Job.id)
        .limit(limit)
        .offset(offset)
        .options(selectinload(Job.webhook_deliveries))  # one query for the page's webhooks
    )
    return Page[JobOut](items=[job_out(j) for j in rows], total=total, limit=limit, offset=offset)


# Built once: the status poll is the API's hot path, and building a select costs more
# than running it.
_JOB_ROW = select(Job.__table__).where(
    Job.id == bindparam("job_id"), Job.owner == bindparam("owner")
)
_DELIVERIES = (
    select(*(WebhookDelivery.__table__.c[name] for name in SUMMARY_FIELDS))
    .where(WebhookDelivery.job_id == bindparam("job_id"))
    .order_by(WebhookDelivery.created_at.desc(), WebhookDelivery.id.desc())
    .limit(DELIVERIES_SHOWN)
)
JobStatus = tuple[Row[Any], list[Row[Any]]]  # the job's row, its latest webhook deliveries


def _read_status(
    database: Database, key: str, job_id: str
) -> tuple[KeyRecord | None, JobStatus | None]:
    """The caller's key and, when it is live, their job's row (and, for a job with a
    webhook, its latest deliveries): one connection, one read transaction, plain columns
    (no ORM objects)."""
    with database.engine.connect() as connection:
        record = lookup(connection, key)
        if record is None:
            return None, None
        params = {"job_id": job_id, "owner": record.principal.owner}
        row = connection.execute(_JOB_ROW, params).first()
        if row is None:
            return record, None
        if row.webhook_url is None:
            return record, (row, [])
        return record, (row, list(connection.execute(_DELIVERIES, {"job_id": job_id})))


async def _job_status(request: Request, credentials: CredentialsDep) -> JobStatus | None:
    """The caller's job for ``GET /v1/jobs/{id}``, authenticated like every route (401,
    403 before anything else) but in one trip to a read thread for the key and the job
    together instead of one for each: clients poll this route, and on a busy machine
    every thread hop is a wait for the GIL and a core."""
    key = presented_key(credentials)
    record, status = await anyio.to_thread.run_sync(
        _read_status,
        request.app.state.database,
        key,
        request.path_params["job_id"],
        limiter=read_threads(request),
    )
    if record is not None:
        await note_use(request, record)
    authorize(request, record)
    return status


@router.get(
    "/{job_id}",
    response_model=JobOut,
    responses={**responses(*AUTH, 422), 304: {"description": "Not modified (If-None-Match)"}},
    summary="Get a job: state, phase, progress, metrics, ETA",
)
async def get_job(
    job_id: JobId,
    status: Annotated[JobStatus | None, Depends(_job_status)],
    if_none_match: Annotated[str | None, Header(max_length=1024)] = None,
) -> Response:
    if status is None:  # no such job, or another owner's
        raise not_found("job", job_id)
    row, deliveries = status
    etag = _etag(row)
    if if_none_match and etag in [t.strip() for t in if_none_match.split(",")]:
        return Response(status_code=304, headers={"ETag": etag})
    # the bytes and headers FastAPI would make of the JobOut, without validating it again
    response = Response(job_out(row, deliveries).model_dump_json(), media_type="application/json")
    response.headers["ETag"] = etag
    response.headers["Cache-Control"] = "no-cache"
    return response


@router.post(
    "/{job_id}/cancel",
    response_model=JobOut,
    responses=responses(*AUTH, 409, 422),
    summary="Cancel: a queued job at once, a running one at its next check",
)
def cancel_job(job_id: JobId, principal: PrincipalDep, session: SessionDep) -> JobOut:
    job = owned_job(session, principal, job_id, lock=True)
    now = _now()
    if job.state == JobState.QUEUED:
        job.state, job.finished_at = JobState.CANCELLED, now
    elif job.state == JobState.RUNNING:
        job.cancel_requested = True
    else:
        raise ApiError(409, "job-finished", f"job '{job_id}' is already {job.state}")
    job.updated_at = now
    job.version += 1
    if job.state == JobState.CANCELLED:  # it ended here: its webhook event, if it has one
        record_job_end(session, job)
    session.commit()
    return job_out(job)


@router.post(
    "/{job_id}/resume",
    response_model=JobOut,
    responses=responses(*AUTH, 409, 422, 503),
    dependencies=[StoreUp],
    summary="Re-queue a cancelled or failed job; it continues from its last checkpoint",
)
def resume_job(
    job_id: JobId, principal: PrincipalDep, session: SessionDep, queue: QueueDep
) -> JobOut:
    job = owned_job(session, principal, job_id, lock=True)
    if job.state not in (JobState.CANCELLED, JobState.FAILED):
        raise ApiError(
            409,
            "job-not-resumable",
            f"job '{job_id}' is {job.state}; only cancelled or failed jobs can be resumed",
        )
    job.state, job.cancel_requested, job.error = JobState.QUEUED, False, None
    job.runner_deaths = 0  # a person asked for it: it gets max_attempts runners again
    job.finished_at, job.updated_at = None, _now()
    job.version += 1
    session.commit()
    enqueue(queue, job.id)
    return job_out(job)


@router.delete(
    "/{job_id}",
    status_code=204,
    response_class=Response,
    responses=responses(*AUTH, 409, 422),
    summary="Delete a finished job with its run folder and artifacts",
)
def delete_job(
    job_id: JobId, principal: PrincipalDep, session: SessionDep, store: StoreDep
) -> Response:
    job = owned_job(session, principal, job_id, lock=True)
    if job.state not in JobState.TERMINAL:
        raise ApiError(409, "job-active", f"job '{job_id}' is {job.state}; cancel it first")
    children = list(session.scalars(select(Job).where(Job.parent_id == job.id)))
    active = [c.id for c in children if c.state not in JobState.TERMINAL]
    if active:
        raise ApiError(
            409,
            "job-active",
            f"job '{job_id}' has mesh jobs still running ({', '.join(active)}); cancel them first",
        )
    session.delete(job)  # its mesh jobs go with it (foreign key cascade)
    session.commit()
    discard(store, [job_key(c.id) for c in children] + [job_key(job_id)])
    return Response(status_code=204)


# --- server-sent events --------------------------------------------------------------


def _snapshot(database: Database, owner: str, job_id: str) -> JobOut | None:
    with database.read() as s:
        job = s.scalar(select(Job).where(Job.id == job_id, Job.owner == owner))
        return None if job is None else job_out(job)


def _sse(event: str, data: str, ident: int | None = None) -> str:
    head = f"id: {ident}\n" if ident is not None else ""
    return (
        head + f"event: {event}\n" + "".join(f"data: {line}\n" for line in data.split("\n")) + "\n"
    )


@router.get(
    "/{job_id}/events",
    response_class=StreamingResponse,
    responses={
        200: {
            "description": "`event: job` with the job (as GET /v1/jobs/{id}) on every change, "
            "`id` = its version; `event: end` after a terminal state, then the stream closes.",
            "content": {"text/event-stream": {"schema": {"type": "string"}}},
        },
        **responses(*AUTH, 422),
    },
    summary="Follow a job as server-sent events",
)
async def job_events(
    job_id: JobId,
    request: Request,
    principal: PrincipalDep,
    database: DatabaseDep,
    settings: SettingsDep,
    last_event_id: Annotated[str | None, Header(max_length=32)] = None,
) -> StreamingResponse:
    first = await run_in_threadpool(_snapshot, database, principal.owner, job_id)
    if first is None:
        raise not_found("job", job_id)
    seen = int(last_event_id) if last_event_id and last_event_id.isdigit() else None

    async def stream() -> AsyncIterator[str]:
        nonlocal seen
        yield f"retry: {int(settings.sse_poll_s * 4000)}\n\n"
        snap: JobOut | None = first
        quiet_since = anyio.current_time()
        while True:
            if snap is None:  # deleted while followed
                yield _sse("end", json.dumps({"state": "deleted"}))
                return
            if snap.version != seen:
                seen = snap.version
                quiet_since = anyio.current_time()
                yield _sse("job", snap.model_dump_json(), snap.version)
            if snap.state in JobState.TERMINAL:
                yield _sse("end", json.dumps({"state": snap.state}))
                return
            if anyio.current_time() - quiet_since >= settings.sse_keepalive_s:
                quiet_since = anyio.current_time()
                yield ": keepalive\n\n"
            await anyio.sleep(settings.sse_poll_s)
            if await request.is_disconnected():
                return
            snap = await run_in_threadpool(_snapshot, database, principal.owner, job_id)

    return StreamingResponse(
        stream(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
