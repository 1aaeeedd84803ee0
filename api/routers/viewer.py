"""The viewer's API side: viewer tokens for job owners, and job lookups for viewer_web.

``POST /v1/jobs/{id}/viewer-token`` (Bearer key, owner-scoped like every job route)
returns a short-lived token that the viewer page uses for its WebSocket and env-map
requests, so the API key never travels in a URL. The rest of the viewer lives in
``viewer_web`` and reaches the database only through :func:`make_lookup`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from fastapi import APIRouter, FastAPI, Request
from pydantic import BaseModel, Field
from sqlalchemy import select

from api.deps import SCOPE_EXTRA, PrincipalDep, SessionDep
from api.problems import responses
from api.routers.jobs import AUTH, JobId, owned_job
from api.service.models import Job
from api.service.sfm_phase import scene_key
from api.service.store import ArtifactStore, StoreUnavailableError, job_run_key
from api.strict_json import StrictJsonRoute
from api.views import job_out
from viewer_web import JobView, ViewerService

router = APIRouter(prefix="/jobs", tags=["viewer"], route_class=StrictJsonRoute)
log = logging.getLogger("glint.viewer")
CHECKPOINT_NAME = "checkpoint.pt"  # core.model.trained's; the API process does not import torch

# The job fields the viewer shows (config and plan stay out: they are large).
STATUS_FIELDS = (
    "id",
    "state",
    "phase",
    "stage",
    "iteration",
    "total_iterations",
    "progress",
    "n_gaussians",
    "loss",
    "metrics",
    "elapsed_s",
    "eta_s",
    "time_left_s",
    "error",
    "version",
)


class ViewerTokenOut(BaseModel):
    token: str = Field(description="pass as ?token= to the viewer WebSocket and env-map URLs")
    expires_at: datetime
    expires_in: int = Field(description="seconds until the token expires")
    websocket: str = Field(description="path of the frame stream, token included")
    envmap: str = Field(description="path of the env map PNG, token included")
    page: str = Field(description="path of the viewer page for this job")


def viewer_status(job: Job) -> dict[str, Any]:
    data = job_out(job).model_dump(mode="json")
    return {k: data[k] for k in STATUS_FIELDS}


def make_lookup(app: FastAPI) -> Callable[[str, str], JobView | None]:
    """(job id, owner) -> JobView | None, reading the app's database and store.

    The viewer reads files: with a bucket, the job's checkpoint is fetched into this
    host's cache whenever it changed (one HEAD per look while unchanged; the viewer looks
    about once a second and reloads the model when the copy is newer), and the scene
    (frozen once its jobs exist; for photos without poses, the job's SfM scene once its
    sfm phase recorded it) once per process. A store that is down keeps the last
    copies."""
    scenes: dict[str, Path | None] = {}

    def scene_folder(store: ArtifactStore, key: str) -> Path | None:
        if key not in scenes:
            folder = store.local(key)
            scenes[key] = folder if folder.is_dir() and any(folder.iterdir()) else None
        return scenes[key]

    def lookup(job_id: str, owner: str) -> JobView | None:
        with app.state.database.read() as s:
            job = s.scalar(select(Job).where(Job.id == job_id, Job.owner == owner))
            if job is None:
                return None
            status, trained, sfm = viewer_status(job), job.id, job.sfm
            if job.parent_id is not None:  # a mesh job: the scene its parent trained on
                trained = job.parent_id
                sfm = s.scalar(select(Job.sfm).where(Job.id == trained))
            key = scene_key(trained, job.scene_id, sfm)
            has_scene = sfm is None or bool(sfm.get("result"))  # SfM done, scene stored
        store: ArtifactStore = app.state.store
        run_key = job_run_key(job_id)
        scene_dir: Path | None = None
        try:
            store.local_file(f"{run_key}/{CHECKPOINT_NAME}")
            scene_dir = scene_folder(store, key) if has_scene else None
        except StoreUnavailableError as exc:
            log.warning("viewer: job %s: %s; showing what this host has", job_id, exc)
        return JobView(store.local_path(run_key), scene_dir, status)

    return lookup


def make_service(app: FastAPI) -> ViewerService:
    """The app's viewer service: ``Settings.viewer_max`` bounds concurrent viewers;
    ``Settings.viewer_secret`` signs their tokens (shared by replicas when set)."""
    settings = app.state.settings
    secret = settings.viewer_secret.encode("utf-8") if settings.viewer_secret else None
    return ViewerService(make_lookup(app), secret=secret, max_viewers=settings.viewer_max)


@router.post(
    "/{job_id}/viewer-token",
    response_model=ViewerTokenOut,
    responses=responses(*AUTH, 422),
    openapi_extra={SCOPE_EXTRA: "read"},  # a POST that changes nothing: viewing is reading
    summary="Get a short-lived token for the browser viewer of a job",
)
def viewer_token(
    job_id: JobId, principal: PrincipalDep, session: SessionDep, request: Request
) -> ViewerTokenOut:
    owned_job(session, principal, job_id)
    service: ViewerService = request.app.state.viewer
    token, expires = service.issue_token(job_id, principal.owner)
    base = f"/v1/jobs/{job_id}/viewer"
    return ViewerTokenOut(
        token=token,
        expires_at=datetime.fromtimestamp(expires, UTC),
        expires_in=int(service.token_ttl_s),
        websocket=f"{base}/ws?token={token}",
        envmap=f"{base}/envmap.png?token={token}",
        page=f"/viewer/{job_id}",
    )
