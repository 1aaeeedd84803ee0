"""Artifacts of a job: the files its run folder holds once it ended, listed and downloaded.

Downloads carry the file's SHA-256 as a strong ETag (stable across restarts and
replicas, unlike mtimes), so clients revalidate with If-None-Match and resume broken
downloads with Range. With a bucket the bytes are streamed through the API (a ranged
GET per request), not redirected to a presigned URL: the owner check guards every
download, the bucket stays private to the servers, and clients see one URL and ETag
whatever the store.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Request
from fastapi.responses import Response
from sqlalchemy import select

from api.deps import PrincipalDep, SessionDep, SettingsDep, StoreDep
from api.pages import Limit, Offset, page_rows
from api.problems import ApiError, not_found, responses
from api.ranges import stored_response
from api.routers.jobs import owned_job
from api.schemas import ArtifactOut, Page
from api.service.models import Artifact
from api.service.store import job_run_key
from api.strict_json import StrictJsonRoute

router = APIRouter(
    prefix="/jobs/{job_id}/artifacts", tags=["artifacts"], route_class=StrictJsonRoute
)
JobId = Annotated[str, Path(max_length=40, description="job id (job_...)")]

DOWNLOAD_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "the file (its Content-Type as listed)",
        "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
    },
    206: {
        "description": "one byte range of the file (Range request)",
        "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
    },
    304: {"description": "not modified (If-None-Match matched the ETag)"},
    **responses(401, 404, 416, 422),
}


def _out(request: Request, job_id: str, a: Artifact) -> ArtifactOut:
    url = str(request.url_for("download_artifact", job_id=job_id, name=a.name).path)
    return ArtifactOut(
        name=a.name, size=a.size, content_type=a.content_type, sha256=a.sha256, url=url
    )


@router.get(
    "",
    response_model=Page[ArtifactOut],
    responses=responses(401, 404, 422),
    summary="List a job's artifacts (by name)",
)
def list_artifacts(
    job_id: JobId,
    request: Request,
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    limit: Limit = 50,
    offset: Offset = 0,
) -> Page[ArtifactOut]:
    owned_job(session, principal, job_id)
    limit = min(limit, settings.page_size_max)
    query = select(Artifact).where(Artifact.job_id == job_id).order_by(Artifact.name)
    rows, total = page_rows(session, query, limit, offset)
    items = [_out(request, job_id, a) for a in rows]
    return Page[ArtifactOut](items=items, total=total, limit=limit, offset=offset)


@router.get(
    "/{name:path}",
    name="download_artifact",
    response_class=Response,
    responses=DOWNLOAD_RESPONSES,
    summary="Download an artifact (ETag, If-None-Match, single Range)",
)
def download_artifact(
    job_id: JobId,
    name: Annotated[str, Path(max_length=1024)],
    request: Request,
    principal: PrincipalDep,
    session: SessionDep,
    store: StoreDep,
) -> Response:
    owned_job(session, principal, job_id)
    art = session.scalar(select(Artifact).where(Artifact.job_id == job_id, Artifact.name == name))
    if art is None:
        raise not_found("artifact", name)
    session.rollback()  # end the read transaction before streaming the body
    key = f"{job_run_key(job_id)}/{art.name}"
    obj = store.stat(key)
    if obj is None:
        raise ApiError(404, "not-found", f"artifact '{name}' is registered but its file is gone")
    return stored_response(
        request,
        store,
        key,
        size=obj.size,
        etag=f'"{art.sha256}"',
        content_type=art.content_type,
        filename=art.name.rsplit("/", 1)[-1],
    )
