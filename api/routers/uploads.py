"""Resumable uploads of scene files: announce, send chunks from an offset, ask the offset.

``POST /v1/scenes/{id}/uploads`` announces a file (path, size, SHA-256) and answers its
upload with the offset to send from: 0 for a new one, the bytes already held for an
unfinished one of the same file (so a client that lost everything, even the upload's
id, resumes by announcing again), or ``complete`` when the scene already holds exactly
that file. ``PATCH`` sends the next chunk. See :mod:`api.resumable` for how chunks are
kept, and docs/api.md (*Resumable uploads*) for the protocol.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Header, Path, Request, Response
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import select

from api.deps import DatabaseDep, JsonBody, PrincipalDep, SessionDep, SettingsDep, StoreDep
from api.pages import Limit, Offset, page_rows
from api.paths import UnsafePathError, clean_relpath
from api.problems import ApiError, FieldError, responses
from api.resumable import (
    advance,
    complete_out,
    finish,
    offset_mismatch,
    owned_upload,
    read_upload,
    upload_out,
)
from api.routers.scenes import owned_scene, require_open
from api.schemas import Page, SceneFileOut, UploadCreate, UploadOut
from api.service.chunk_uploads import chunk_key, uploads_key
from api.service.discard import discard
from api.service.models import SceneFile, Upload, new_id
from api.strict_json import StrictJsonRoute
from api.uploads import check_content_length, receive_body, too_large
from api.views import scene_totals

router = APIRouter(
    prefix="/scenes/{scene_id}/uploads", tags=["uploads"], route_class=StrictJsonRoute
)

SceneId = Annotated[str, Path(max_length=40, description="scene id (scn_...)")]
UploadId = Annotated[str, Path(max_length=40, description="upload id (upl_...)")]
AUTH = (401, 404)
CHUNK_TYPES = ("application/offset+octet-stream", "application/octet-stream")

CHUNK_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "description": "the file's bytes from `Upload-Offset` on (at most `chunk_max_bytes`)",
        "content": {t: {"schema": {"type": "string", "format": "binary"}} for t in CHUNK_TYPES},
    }
}


def _refuse(status: int, slug: str, field: str, message: str) -> ApiError:
    return ApiError(status, slug, message, errors=[FieldError(field=field, message=message)])


@router.post(
    "",
    status_code=201,
    response_model=UploadOut,
    responses=responses(400, *AUTH, 409, 413, 415, 422),
    dependencies=[JsonBody],
    summary="Start (or find again) a resumable upload of one file",
    description="201 with a new upload at offset 0; 200 with the unfinished upload of the "
    "same path, size and SHA-256 (its offset says what the server holds), or 200 with "
    "`state: complete` when the scene already holds exactly this file.",
)
def create_upload(
    scene_id: SceneId,
    body: UploadCreate,
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    store: StoreDep,
    database: DatabaseDep,
    response: Response,
) -> UploadOut:
    scene = owned_scene(session, principal, scene_id, lock=True)
    require_open(scene)
    try:
        path = clean_relpath(body.path, settings.max_path_length)
    except UnsafePathError as exc:
        raise _refuse(422, "unsafe-path", "body.path", f"'{body.path}': {exc}") from None
    sha = body.sha256.lower()
    held = session.scalar(
        select(SceneFile).where(SceneFile.scene_id == scene_id, SceneFile.path == path)
    )
    if held is not None and held.size == body.size and held.sha256 == sha:
        response.status_code = 200
        return complete_out(scene_id, SceneFileOut.model_validate(held), settings)
    found = session.scalar(
        select(Upload).where(
            Upload.scene_id == scene_id,
            Upload.path == path,
            Upload.size == body.size,
            Upload.sha256 == sha,
        )
    )
    if found is not None:
        response.status_code = 200
        return upload_out(found, settings)
    if body.size > settings.max_file_bytes:
        raise _refuse(
            413,
            "too-large",
            "body.size",
            f"'{path}' has {body.size} bytes; the limit is {settings.max_file_bytes}",
        )
    n, total = scene_totals(session, [scene_id]).get(scene_id, (0, 0))
    total += body.size - (held.size if held is not None else 0)
    if total > settings.max_scene_bytes:
        raise _refuse(
            413,
            "too-large",
            "body.size",
            f"the scene would hold {total} bytes; the limit is {settings.max_scene_bytes}",
        )
    if held is None and n + 1 > settings.max_scene_files:
        raise _refuse(
            413, "too-large", "body.path", f"the scene holds {n} files, the most it may hold"
        )
    up = Upload(
        id=new_id("upl"),
        scene_id=scene_id,
        path=path,
        size=body.size,
        sha256=sha,
        offset=0,
        chunks=[],
    )
    session.add(up)
    session.commit()
    if up.size == 0:  # nothing to send: the empty file is complete at once
        response.status_code = 200
        return finish(database, store, principal, up, settings)
    return upload_out(up, settings)


@router.get(
    "",
    response_model=Page[UploadOut],
    responses=responses(*AUTH, 422),
    summary="List a scene's unfinished uploads",
)
def list_uploads(
    scene_id: SceneId,
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    limit: Limit = 50,
    offset: Offset = 0,
) -> Page[UploadOut]:
    owned_scene(session, principal, scene_id)
    limit = min(limit, settings.page_size_max)
    query = select(Upload).where(Upload.scene_id == scene_id).order_by(Upload.path, Upload.id)
    rows, total = page_rows(session, query, limit, offset)
    items = [upload_out(u, settings) for u in rows]
    return Page[UploadOut](items=items, total=total, limit=limit, offset=offset)


@router.get(
    "/{upload_id}",
    response_model=UploadOut,
    responses=responses(*AUTH, 422),
    summary="An unfinished upload: its offset is what the server holds",
)
def get_upload(
    scene_id: SceneId,
    upload_id: UploadId,
    principal: PrincipalDep,
    session: SessionDep,
    settings: SettingsDep,
    response: Response,
) -> UploadOut:
    _, up = owned_upload(session, principal, scene_id, upload_id)
    response.headers["Upload-Offset"] = str(up.offset)
    return upload_out(up, settings)


@router.patch(
    "/{upload_id}",
    response_model=UploadOut,
    responses=responses(400, *AUTH, 409, 413, 415, 422),
    openapi_extra=CHUNK_BODY,
    summary="Send the next chunk, from Upload-Offset on",
    description="A chunk that arrives whole advances the offset; one cut off midway is "
    "dropped whole. A wrong `Upload-Offset` answers 409 `offset-mismatch` with the "
    "server's `offset`. The last chunk joins the file, checks its SHA-256 (422 "
    "`checksum-mismatch` resets the upload to 0) and answers `state: complete`.",
)
async def send_chunk(
    scene_id: SceneId,
    upload_id: UploadId,
    request: Request,
    principal: PrincipalDep,
    settings: SettingsDep,
    database: DatabaseDep,
    store: StoreDep,
    response: Response,
    upload_offset: Annotated[
        str | None, Header(alias="Upload-Offset", description="where this chunk starts")
    ] = None,
) -> UploadOut:
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype not in CHUNK_TYPES:
        raise ApiError(
            415,
            "unsupported-media-type",
            f"a chunk is sent as application/offset+octet-stream, got '{ctype or 'nothing'}'",
        )
    if upload_offset is None or not upload_offset.isdigit():
        raise _refuse(
            400,
            "bad-request",
            "header.upload-offset",
            "Upload-Offset must be the byte offset this chunk starts at (a non-negative integer)",
        )
    start = int(upload_offset)
    up = await run_in_threadpool(read_upload, database, principal, scene_id, upload_id)
    if start != up.offset:
        raise offset_mismatch(upload_id, start, up.offset)
    left = up.size - up.offset
    if left > 0:
        limit = min(settings.upload_chunk_max_bytes, left)
        check_content_length(request, limit)
        key = chunk_key(scene_id, upload_id, start)
        try:
            pending = await receive_body(request, store, key, limit, settings.upload_chunk_bytes)
        except ApiError as exc:
            if exc.status == 413:  # say why in this protocol's terms
                raise too_large(
                    f"a chunk may carry at most {limit} bytes here (the file has {left} left "
                    f"from offset {start}; chunk_max_bytes {settings.upload_chunk_max_bytes})"
                ) from None
            raise
        if pending.size == 0:
            await run_in_threadpool(pending.abort)
            raise ApiError(400, "bad-request", "the chunk is empty: send the bytes from the offset")
        result = await run_in_threadpool(pending.commit)
        try:
            up = await run_in_threadpool(
                advance, database, principal, scene_id, upload_id, start, key, result.size
            )
        except BaseException:
            await run_in_threadpool(discard, store, [key])
            raise
    response.headers["Upload-Offset"] = str(up.offset)
    if up.offset < up.size:
        return upload_out(up, settings)
    return await run_in_threadpool(finish, database, store, principal, up, settings)


@router.delete(
    "/{upload_id}",
    status_code=204,
    response_class=Response,
    responses=responses(*AUTH, 422),
    summary="Abandon an unfinished upload (its chunks go)",
)
def delete_upload(
    scene_id: SceneId,
    upload_id: UploadId,
    principal: PrincipalDep,
    session: SessionDep,
    store: StoreDep,
) -> Response:
    _, up = owned_upload(session, principal, scene_id, upload_id, lock=True)
    session.delete(up)
    session.commit()
    discard(store, [uploads_key(scene_id, upload_id)])
    return Response(status_code=204)
