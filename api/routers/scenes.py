"""Scenes: create, upload files (multipart or one archive), commit (= validate), read, delete.

A scene is ``open`` while files are uploaded, ``validating`` during a commit and
``ready`` once the core loaders accepted it; a failed commit re-opens it with the
problem recorded, so the user can replace the faulty file and commit again. Files
are frozen once the scene is ready (409), because jobs train on them.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Annotated, Any

from fastapi import APIRouter, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from api.archives import ARCHIVE_TYPES, ArchiveLimits, extract_archive
from api.auth import Principal
from api.deps import (
    DatabaseDep,
    JsonBody,
    PrincipalDep,
    ScratchDep,
    SessionDep,
    SettingsDep,
    StoreDep,
)
from api.idempotent import IdempotencyKey, commit_or_replay, replayed
from api.pages import Limit, Offset, page_rows
from api.problems import ApiError, not_found, responses
from api.schemas import Page, SceneCreate, SceneFileOut, SceneOut, UploadResult
from api.service.chunk_uploads import drop_scene_uploads
from api.service.db import Database
from api.service.discard import discard
from api.service.models import Job, Scene, SceneFile, SceneState, new_id
from api.service.settings import Settings
from api.service.store import (
    ArtifactStore,
    StoreError,
    StoreUnavailableError,
    scene_files_key,
    scene_key,
)
from api.strict_json import StrictJsonRoute
from api.uploads import Limits, StagedSet, receive_body, receive_multipart, too_large
from api.validation import validate_scene
from api.views import scene_out, scene_out_one, scene_totals

router = APIRouter(prefix="/scenes", tags=["scenes"], route_class=StrictJsonRoute)

SceneId = Annotated[str, Path(max_length=40, description="scene id (scn_...)")]
AUTH = (401, 404)
CREATE_ROUTE = "POST /v1/scenes"

MULTIPART_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "description": "one or more file parts; each part's filename is its path inside "
        "the scene (e.g. `train/r_0.png`). Streamed to the store, never held in memory.",
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "properties": {
                        "files": {"type": "array", "items": {"type": "string", "format": "binary"}}
                    },
                    "required": ["files"],
                }
            }
        },
    }
}
ARCHIVE_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "description": "a zip or tar (optionally gzip/bzip2/xz) archive of scene files",
        "content": {
            t: {"schema": {"type": "string", "format": "binary"}}
            for t in ("application/zip", "application/x-tar", "application/gzip")
        },
    }
}


def _now() -> datetime:
    return datetime.now(UTC)


def owned_scene(
    session: Session, principal: Principal, scene_id: str, *, lock: bool = False
) -> Scene:
    """The caller's scene, or 404 (also for other owners' scenes: ids are not leaked)."""
    q = select(Scene).where(Scene.id == scene_id, Scene.owner == principal.owner)
    if lock:
        q = q.with_for_update()
    scene = session.scalar(q)
    if scene is None:
        raise not_found("scene", scene_id)
    return scene


def require_open(scene: Scene) -> None:
    if scene.state == SceneState.READY:
        raise ApiError(409, "scene-committed", f"scene '{scene.id}' is committed; files are frozen")
    if scene.state == SceneState.VALIDATING:
        raise ApiError(409, "scene-validating", f"scene '{scene.id}' is being validated")


@router.post(
    "",
    status_code=201,
    response_model=SceneOut,
    responses=responses(400, 401, 415, 422),
    dependencies=[JsonBody],
    summary="Create an empty scene",
)
def create_scene(
    body: SceneCreate,
    principal: PrincipalDep,
    session: SessionDep,
    response: Response,
    idempotency_key: IdempotencyKey = None,
) -> SceneOut:
    request_body = body.model_dump(mode="json")
    existing = replayed(session, principal, CREATE_ROUTE, idempotency_key, request_body, response)
    if existing is None:
        scene = Scene(id=new_id("scn"), owner=principal.owner, name=body.name)
        session.add(scene)
        session.flush()
        existing = commit_or_replay(
            session, principal, CREATE_ROUTE, idempotency_key, request_body, scene.id, response
        )
        if existing is None:
            return scene_out(scene)
    return scene_out_one(session, owned_scene(session, principal, existing))


@router.get("", response_model=Page[SceneOut], responses=responses(401, 422), summary="List scenes")
def list_scenes(
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    state: Annotated[str | None, Query(pattern="^(open|validating|ready)$")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    offset: Annotated[int, Query(ge=0, le=2**31)] = 0,
) -> Page[SceneOut]:
    limit = min(limit, settings.page_size_max)
    where = [Scene.owner == principal.owner]
    if state:
        where.append(Scene.state == state)
    total = session.scalar(select(func.count()).select_from(Scene).where(*where)) or 0
    rows = list(
        session.scalars(
            select(Scene)
            .where(*where)
            .order_by(Scene.created_at.desc(), Scene.id)
            .limit(limit)
            .offset(offset)
        )
    )
    totals = scene_totals(session, [s.id for s in rows])
    items = [scene_out(s, totals.get(s.id, (0, 0))) for s in rows]
    return Page[SceneOut](items=items, total=total, limit=limit, offset=offset)


@router.get("/{scene_id}", response_model=SceneOut, responses=responses(*AUTH, 422))
def get_scene(scene_id: SceneId, principal: PrincipalDep, session: SessionDep) -> SceneOut:
    return scene_out_one(session, owned_scene(session, principal, scene_id))


@router.delete(
    "/{scene_id}",
    status_code=204,
    response_class=Response,
    responses=responses(*AUTH, 409, 422),
    summary="Delete a scene and its files (refused while jobs use it)",
)
def delete_scene(
    scene_id: SceneId, principal: PrincipalDep, session: SessionDep, store: StoreDep
) -> Response:
    scene = owned_scene(session, principal, scene_id, lock=True)
    if scene.state == SceneState.VALIDATING:
        raise ApiError(409, "scene-validating", f"scene '{scene_id}' is being validated")
    n_jobs = session.scalar(select(func.count()).select_from(Job).where(Job.scene_id == scene_id))
    if n_jobs:
        raise ApiError(
            409, "scene-in-use", f"scene '{scene_id}' has {n_jobs} job(s); delete them first"
        )
    session.delete(scene)
    session.commit()
    discard(store, [scene_key(scene_id)])
    return Response(status_code=204)


@router.get(
    "/{scene_id}/files",
    response_model=Page[SceneFileOut],
    responses=responses(*AUTH, 422),
    summary="List a scene's files (by path)",
)
def list_files(
    scene_id: SceneId,
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    limit: Limit = 50,
    offset: Offset = 0,
) -> Page[SceneFileOut]:
    owned_scene(session, principal, scene_id)
    limit = min(limit, settings.page_size_max)
    query = select(SceneFile).where(SceneFile.scene_id == scene_id).order_by(SceneFile.path)
    rows, total = page_rows(session, query, limit, offset)
    items = [SceneFileOut.model_validate(r) for r in rows]
    return Page[SceneFileOut](items=items, total=total, limit=limit, offset=offset)


@router.delete(
    "/{scene_id}/files/{path:path}",
    status_code=204,
    response_class=Response,
    responses=responses(*AUTH, 409, 422),
    summary="Remove one uploaded file (open scenes only)",
)
def delete_file(
    scene_id: SceneId,
    path: Annotated[str, Path(max_length=1024)],
    principal: PrincipalDep,
    session: SessionDep,
    store: StoreDep,
) -> Response:
    scene = owned_scene(session, principal, scene_id, lock=True)
    require_open(scene)
    row = session.scalar(
        select(SceneFile).where(SceneFile.scene_id == scene_id, SceneFile.path == path)
    )
    if row is None:
        raise not_found("file", path)
    store.delete(f"{scene_files_key(scene_id)}/{path}")  # a store that is down: 503, kept
    session.delete(row)
    scene.updated_at = _now()
    session.commit()
    return Response(status_code=204)


# --- uploads -------------------------------------------------------------------------


def upload_budget(
    database: Database, principal: Principal, scene_id: str, settings: Settings
) -> Limits:
    """What the scene can still take; 404/409 before a byte of the body is read."""
    with database.read() as s:
        scene = owned_scene(s, principal, scene_id)
        require_open(scene)
        n, total = scene_totals(s, [scene_id]).get(scene_id, (0, 0))
    return Limits(
        max_file_bytes=settings.max_file_bytes,
        max_total_bytes=max(settings.max_scene_bytes - total, 0),
        max_files=max(settings.max_scene_files - n, 0),
        max_path_length=settings.max_path_length,
    )


def _conflicts(paths: set[str], existing: set[str]) -> str | None:
    """A path that would be both a file and a folder, if any."""
    everything = paths | existing
    for p in paths:
        parts = p.split("/")
        for i in range(1, len(parts)):
            if "/".join(parts[:i]) in everything:
                return "/".join(parts[:i])
        prefix = p + "/"
        if any(e.startswith(prefix) for e in everything):
            return p
    return None


def commit_staged(
    database: Database,
    store: ArtifactStore,
    principal: Principal,
    scene_id: str,
    staged: StagedSet,
    settings: Settings,
) -> UploadResult:
    """Make staged files visible and record them, atomically with the scene's state check."""
    committed: list[str] = []
    try:
        with database.write() as s:
            scene = owned_scene(s, principal, scene_id, lock=True)
            require_open(scene)
            existing = {
                r.path: r
                for r in s.scalars(select(SceneFile).where(SceneFile.scene_id == scene_id))
            }
            new_paths = {f.path for f in staged.files}
            total = sum(r.size for p, r in existing.items() if p not in new_paths)
            total += staged.total_bytes
            count = len(existing.keys() | new_paths)
            if total > settings.max_scene_bytes:
                raise too_large(
                    f"scene would hold {total} bytes; the limit is {settings.max_scene_bytes}"
                )
            if count > settings.max_scene_files:
                raise too_large(
                    f"scene would hold {count} files; the limit is {settings.max_scene_files}"
                )
            clash = _conflicts(new_paths, set(existing) - new_paths)
            if clash:
                raise ApiError(409, "path-conflict", f"'{clash}' would be both a file and a folder")
            out = []
            now = _now()
            for f in staged.files:
                res = f.pending.commit()
                committed.append(f.path)
                row = existing.get(f.path)
                if row is None:
                    row = SceneFile(
                        scene_id=scene_id, path=f.path, size=res.size, sha256=res.sha256
                    )
                    s.add(row)
                else:
                    row.size, row.sha256, row.created_at = res.size, res.sha256, now
                out.append(SceneFileOut(path=f.path, size=res.size, sha256=res.sha256))
            scene.updated_at = now
            s.flush()
            totals = scene_totals(s, [scene_id]).get(scene_id, (0, 0))
            result = UploadResult(scene=scene_out(scene, totals), files=out)
    except BaseException as exc:
        staged.abort()  # whatever was not committed yet
        for path in committed:  # and whatever was, since the transaction rolled back
            store.delete(f"{scene_files_key(scene_id)}/{path}")
        if isinstance(exc, StoreError):
            raise ApiError(409, "path-conflict", str(exc)) from None
        raise
    return result


def key_for(scene_id: str) -> Callable[[str], str]:
    base = scene_files_key(scene_id)
    return lambda path: f"{base}/{path}"


@router.post(
    "/{scene_id}/files",
    status_code=201,
    response_model=UploadResult,
    responses=responses(400, *AUTH, 409, 413, 415, 422),
    openapi_extra=MULTIPART_BODY,
    summary="Upload scene files (multipart, streamed; repeatable)",
)
async def upload_files(
    scene_id: SceneId,
    request: Request,
    principal: PrincipalDep,
    settings: SettingsDep,
    database: DatabaseDep,
    store: StoreDep,
) -> UploadResult:
    limits = await run_in_threadpool(upload_budget, database, principal, scene_id, settings)
    staged = await receive_multipart(
        request, store, key_for(scene_id), limits, settings.upload_chunk_bytes
    )
    return await run_in_threadpool(
        commit_staged, database, store, principal, scene_id, staged, settings
    )


@router.post(
    "/{scene_id}/archive",
    status_code=201,
    response_model=UploadResult,
    responses=responses(400, *AUTH, 409, 413, 415, 422),
    openapi_extra=ARCHIVE_BODY,
    summary="Upload scene files as one zip or tar archive (unpacked safely)",
)
async def upload_archive(
    scene_id: SceneId,
    request: Request,
    principal: PrincipalDep,
    settings: SettingsDep,
    database: DatabaseDep,
    store: StoreDep,
    scratch: ScratchDep,
) -> UploadResult:
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype not in ARCHIVE_TYPES:
        raise ApiError(
            415,
            "unsupported-media-type",
            f"expected an archive (application/zip, application/x-tar, application/gzip, ...), "
            f"got '{ctype or 'nothing'}'",
        )
    limits = await run_in_threadpool(upload_budget, database, principal, scene_id, settings)
    incoming = f"tmp/incoming/{uuid.uuid4().hex}"
    pending = await receive_body(  # spooled on local disk: archives are read out of order
        request, scratch, incoming, settings.max_archive_bytes, settings.upload_chunk_bytes
    )
    try:
        await run_in_threadpool(pending.commit)
        archive_limits = ArchiveLimits(
            max_files=limits.max_files,
            max_file_bytes=limits.max_file_bytes,
            max_total_bytes=limits.max_total_bytes,
            max_ratio=settings.max_archive_ratio,
            max_path_length=limits.max_path_length,
        )
        staged = await run_in_threadpool(
            extract_archive, scratch.path(incoming), store, key_for(scene_id), archive_limits
        )
    finally:
        await run_in_threadpool(scratch.delete, incoming)
    return await run_in_threadpool(
        commit_staged, database, store, principal, scene_id, staged, settings
    )


# --- commit --------------------------------------------------------------------------


@router.post(
    "/{scene_id}/commit",
    response_model=SceneOut,
    responses=responses(*AUTH, 409, 422),
    summary="Freeze the files and validate the scene (format auto-detected)",
    description="Loads the scene with the core loaders. Success: the scene is `ready` and "
    "carries a validation report. Failure: 422 naming the file and field at fault; the "
    "scene stays `open` so the faulty file can be replaced.",
)
def commit_scene(
    scene_id: SceneId,
    request: Request,
    principal: PrincipalDep,
    database: DatabaseDep,
    store: StoreDep,
) -> SceneOut:
    with database.write() as s:
        scene = owned_scene(s, principal, scene_id, lock=True)
        require_open(scene)
        n, _ = scene_totals(s, [scene_id]).get(scene_id, (0, 0))
        if n == 0:
            raise ApiError(422, "no-files", f"scene '{scene_id}' has no files to validate")
        scene.state = SceneState.VALIDATING
    problem: ApiError | None = None
    report = None
    store_down = False
    try:
        with request.app.state.validation_slots:  # loading scenes is memory-hungry
            # the scene's files on this host (with a bucket: a local copy, fetched now)
            report = validate_scene(store.local(scene_files_key(scene_id)))
    except ApiError as exc:
        problem = exc
    except StoreUnavailableError:
        store_down = True  # not the scene's fault: it stays open as it was, 503
        raise
    finally:
        with database.write() as s:
            scene = s.get(Scene, scene_id)
            assert scene is not None
            now = _now()
            if report is not None:
                scene.state, scene.format, scene.report = SceneState.READY, report["format"], report
                scene.last_error, scene.committed_at = None, now
            else:
                scene.state = SceneState.OPEN
                if not store_down:
                    scene.last_error = _problem_dict(problem, scene_id)
            scene.updated_at = now
            s.flush()
            out = scene_out_one(s, scene)
    if problem is not None:
        raise problem
    drop_scene_uploads(database, store, scene_id)  # a ready scene takes no more chunks
    return out


def _problem_dict(problem: ApiError | None, scene_id: str) -> dict[str, Any]:
    if problem is None:
        return {
            "type": "urn:glint:problem:internal-error",
            "title": "Internal error",
            "status": 500,
        }
    return {
        "type": f"urn:glint:problem:{problem.slug}",
        "title": problem.title,
        "status": problem.status,
        "detail": problem.detail,
        "instance": f"/v1/scenes/{scene_id}/commit",
        "errors": [e.model_dump() for e in problem.errors or []],
    }
