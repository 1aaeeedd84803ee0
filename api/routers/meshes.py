"""Meshes of a finished training job: re-extraction on request, listed per job.

A mesh extraction is a job of its own (``kind: mesh``, ``parent_id`` = the training
job): it is queued like a training job (on a Celery worker when one runs, in the
embedded runner otherwise), followed with ``GET /v1/jobs/{id}`` and its events,
cancelled with ``POST /v1/jobs/{id}/cancel``, and its files are its artifacts
(``mesh.ply``, ``mesh.glb``, ``mesh.obj``, ``mesh.json``, ``mesh_preview.png``).

With ``asset`` in the body the job then bakes a relightable asset from that mesh
(``core.asset``): ``asset.glb``, ``asset.json``, ``asset_preview.png`` and, when the
model has an environment map, ``asset_env.hdr`` / ``asset_env.exr`` join its artifacts;
the viewer's mesh view (``/viewer/{id}/mesh``) shows them.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Response

from api.deps import JsonBody, PrincipalDep, QueueDep, SessionDep, SettingsDep, StoreDep, StoreUp
from api.idempotent import IdempotencyKey, commit_or_replay, replayed
from api.job_webhook import job_webhook, with_made_secret
from api.problems import ApiError, FieldError, responses
from api.routers.jobs import AUTH, JobId, enqueue, job_page, owned_job
from api.schemas import JobOut, MeshCreate, Page
from api.service.models import Job, JobKind, JobState, new_id
from api.service.store import job_run_key
from api.strict_json import StrictJsonRoute
from api.views import job_out

router = APIRouter(prefix="/jobs", tags=["meshes"], route_class=StrictJsonRoute)

CHECKPOINT = "checkpoint.pt"
OUTPUTS = "outputs.json"


def _too_fine(field: str, detail: str) -> ApiError:
    return ApiError(
        422,
        "grid-too-large",
        detail,
        errors=[FieldError(field=f"body.{field}", message=detail)],
    )


@router.post(
    "/{job_id}/meshes",
    status_code=201,
    response_model=JobOut,
    responses=responses(400, *AUTH, 409, 415, 422, 503),
    dependencies=[JsonBody, StoreUp],
    summary="Extract a mesh from a finished training job (queued as a job of its own)",
)
def create_mesh(
    job_id: JobId,
    body: MeshCreate,
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    store: StoreDep,
    queue: QueueDep,
    response: Response,
    idempotency_key: IdempotencyKey = None,
) -> JobOut:
    route, request_body = f"POST /v1/jobs/{job_id}/meshes", body.model_dump(mode="json")
    existing = replayed(session, principal, route, idempotency_key, request_body, response)
    if existing is not None:  # a retry: answer the mesh job the first request made
        return job_out(owned_job(session, principal, existing))
    parent = owned_job(session, principal, job_id)
    if parent.kind != JobKind.TRAIN:
        raise ApiError(
            409, "not-a-training-job", f"job '{job_id}' is a {parent.kind} job; mesh its parent"
        )
    if parent.state != JobState.SUCCEEDED:
        raise ApiError(
            409,
            "job-not-finished",
            f"job '{job_id}' is {parent.state}; meshes are extracted from succeeded jobs",
        )
    run = job_run_key(parent.id)
    if store.stat(f"{run}/{CHECKPOINT}") is None:
        raise ApiError(409, "no-checkpoint", f"job '{job_id}' has no checkpoint to mesh from")
    limit = settings.mesh_max_resolution
    if body.voxel is None and body.resolution > limit:
        raise _too_fine(
            "resolution", f"resolution {body.resolution} is beyond this server's limit of {limit}"
        )
    if body.voxel is not None:
        side = _box_side(store.local_file(f"{run}/{OUTPUTS}"))
        if side is not None and side / body.voxel > limit:
            raise _too_fine(
                "voxel",
                f"voxel {body.voxel:g} gives about {math.ceil(side / body.voxel)} voxels along "
                f"the scene's box (side {side:.4g}), beyond this server's limit of {limit}",
            )
    hook = job_webhook(session, principal, body.webhook, settings)  # 422: forbidden address
    mesh = Job(
        id=new_id("job"),
        owner=principal.owner,
        scene_id=parent.scene_id,
        kind=JobKind.MESH,
        parent_id=parent.id,
        config=body.model_dump(mode="json", exclude={"webhook"}),  # mesh_run's parameters
        total_iterations=0,
        **hook.columns(),
    )
    session.add(mesh)
    session.flush()
    existing = commit_or_replay(
        session, principal, route, idempotency_key, request_body, mesh.id, response
    )
    if existing is not None:  # a request with the same key won the race
        return job_out(owned_job(session, principal, existing))
    enqueue(queue, mesh.id)
    return with_made_secret(job_out(mesh), hook)


def _box_side(outputs: Path | None) -> float | None:
    """The scene box's side (2 × radius) recorded by the training job's export."""
    if outputs is None:
        return None
    try:
        data = json.loads(outputs.read_text())
        return 2.0 * float(data["scene_box"]["radius"])
    except (OSError, ValueError, KeyError, TypeError):
        return None  # an older run: the runner checks the grid when it is built


@router.get(
    "/{job_id}/meshes",
    response_model=Page[JobOut],
    responses=responses(*AUTH, 422),
    summary="List the mesh extractions of a training job, newest first",
)
def list_meshes(
    job_id: JobId,
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    offset: Annotated[int, Query(ge=0, le=2**31)] = 0,
) -> Page[JobOut]:
    parent = owned_job(session, principal, job_id)
    limit = min(limit, settings.page_size_max)
    where = [Job.parent_id == parent.id, Job.owner == principal.owner]
    return job_page(session, where, limit, offset)
