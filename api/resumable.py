"""Resumable uploads: one file in chunks, each stored whole, joined and checked at the end.

The protocol (docs/api.md, *Resumable uploads*) is "chunks with offsets", tus's core idea
in the API's own REST shape: the client announces a file (path, size, SHA-256), then
sends ``PATCH`` requests carrying the bytes from ``Upload-Offset`` on. Each chunk that
arrives whole becomes an object of its own (``scenes/{id}/uploads/{upload}/{offset}-…``)
and advances the offset in the database with a compare-and-set, so the offset is always
exactly what the store holds: a chunk cut off midway leaves nothing, two clients racing
on one offset cannot both win, and a client that died asks the offset and sends the
rest. The last chunk joins the pieces into the scene file (hashed on the way, refused
and reset on a mismatch) through the same write-then-commit path as a multipart upload.
Chunks live in the store, not on one API host, so any replica can take the next one.
"""

from __future__ import annotations

import hashlib
from datetime import UTC, datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from api.auth import Principal
from api.problems import ApiError, FieldError
from api.routers.scenes import commit_staged, key_for, owned_scene, require_open
from api.schemas import SceneFileOut, UploadOut
from api.service.chunk_uploads import uploads_key
from api.service.db import Database
from api.service.discard import discard
from api.service.models import Scene, Upload
from api.service.settings import Settings
from api.service.store import ArtifactStore
from api.uploads import Staged, StagedSet

READ_BYTES = 1 << 20


def upload_out(up: Upload, settings: Settings) -> UploadOut:
    return UploadOut(
        id=up.id,
        scene_id=up.scene_id,
        path=up.path,
        size=up.size,
        sha256=up.sha256,
        offset=up.offset,
        state="open",
        chunk_max_bytes=settings.upload_chunk_max_bytes,
        file=None,
        created_at=up.created_at,
        updated_at=up.updated_at,
    )


def complete_out(scene_id: str, file: SceneFileOut, settings: Settings) -> UploadOut:
    return UploadOut(
        id=None,
        scene_id=scene_id,
        path=file.path,
        size=file.size,
        sha256=file.sha256,
        offset=file.size,
        state="complete",
        chunk_max_bytes=settings.upload_chunk_max_bytes,
        file=file,
        created_at=None,
        updated_at=None,
    )


def offset_mismatch(upload_id: str, sent: int, current: int) -> ApiError:
    return ApiError(
        409,
        "offset-mismatch",
        f"upload '{upload_id}' holds {current} bytes; a chunk must start at Upload-Offset: "
        f"{current}, not {sent}",
        errors=[FieldError(field="header.upload-offset", message=f"expected {current}")],
        headers={"Upload-Offset": str(current)},
        extensions={"offset": current},
    )


def owned_upload(
    session: Session, principal: Principal, scene_id: str, upload_id: str, *, lock: bool = False
) -> tuple[Scene, Upload]:
    """The caller's scene and its unfinished upload, or 404 (also for other owners')."""
    scene = owned_scene(session, principal, scene_id, lock=lock)
    query = select(Upload).where(Upload.id == upload_id, Upload.scene_id == scene_id)
    up = session.scalar(query.with_for_update() if lock else query)
    if up is None:
        raise ApiError(
            404,
            "not-found",
            f"upload '{upload_id}' not found in scene '{scene_id}' (finished uploads are "
            "files: GET /v1/scenes/{id}/files)",
        )
    return scene, up


def read_upload(database: Database, principal: Principal, scene_id: str, upload_id: str) -> Upload:
    """The caller's unfinished upload on an open scene (404 / 409 otherwise), detached."""
    with database.read() as s:
        scene, up = owned_upload(s, principal, scene_id, upload_id)
        require_open(scene)
        s.expunge(up)
    return up


def advance(
    database: Database,
    principal: Principal,
    scene_id: str,
    upload_id: str,
    expected: int,
    key: str,
    size: int,
) -> Upload:
    """Record a stored chunk if the upload still holds exactly ``expected`` bytes.

    Raises 409 ``offset-mismatch`` (the caller deletes its chunk) when another request
    moved the offset first, and 404/409 when the upload or the scene's openness is gone.
    """
    with database.write() as s:
        scene, up = owned_upload(s, principal, scene_id, upload_id, lock=True)
        require_open(scene)
        if up.offset != expected:
            raise offset_mismatch(upload_id, expected, up.offset)
        up.chunks = [*up.chunks, [expected, key]]
        up.offset = expected + size
        up.updated_at = datetime.now(UTC)
        s.flush()
        s.expunge(up)
    return up


def reset(database: Database, store: ArtifactStore, up: Upload) -> None:
    """Forget every chunk (after a checksum mismatch): the client starts again at 0."""
    with database.write() as s:
        row = s.get(Upload, up.id)
        if row is not None:
            row.chunks, row.offset, row.updated_at = [], 0, datetime.now(UTC)
    discard(store, [key for _, key in up.chunks])


def finish(
    database: Database,
    store: ArtifactStore,
    principal: Principal,
    up: Upload,
    settings: Settings,
) -> UploadOut:
    """Join the chunks into the scene file, check its SHA-256, record it, drop the upload."""
    pending = store.begin(key_for(up.scene_id)(up.path))
    digest = hashlib.sha256()
    try:
        for _, key in up.chunks:
            with store.open(key) as f:
                while data := f.read(READ_BYTES):
                    digest.update(data)
                    pending.write(data)
        pending.seal()
    except BaseException:
        pending.abort()
        raise
    if pending.size != up.size or digest.hexdigest() != up.sha256:
        pending.abort()
        reset(database, store, up)
        raise ApiError(
            422,
            "checksum-mismatch",
            f"'{up.path}': the {pending.size} bytes received have SHA-256 {digest.hexdigest()}, "
            f"not the announced {up.sha256}; the upload was reset to offset 0, send the file "
            "again",
            errors=[FieldError(field="body.sha256", message="does not match the bytes received")],
            extensions={"offset": 0},
        )
    result = commit_staged(
        database, store, principal, up.scene_id, StagedSet([Staged(up.path, pending)]), settings
    )
    with database.write() as s:
        row = s.get(Upload, up.id)
        if row is not None:
            s.delete(row)
    discard(store, [uploads_key(up.scene_id, up.id)])
    return complete_out(up.scene_id, result.files[0], settings)
