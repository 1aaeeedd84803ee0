"""Where resumable uploads keep their chunks, and how unfinished ones go away.

Shared by the upload routes (api/resumable.py), the scene commit (a ready scene takes
no more chunks) and the store sweep (uploads nobody finished).
"""

from __future__ import annotations

import uuid
from datetime import UTC, datetime, timedelta

from sqlalchemy import delete, select

from api.service.db import Database
from api.service.discard import discard
from api.service.models import Upload
from api.service.store import ArtifactStore, scene_key


def uploads_key(scene_id: str, upload_id: str | None = None) -> str:
    """A scene's unfinished uploads keep their chunks here: beside its files, not in them."""
    base = f"{scene_key(scene_id)}/uploads"
    return base if upload_id is None else f"{base}/{upload_id}"


def chunk_key(scene_id: str, upload_id: str, offset: int) -> str:
    """One chunk's object; unique per request, so two racing requests never share one."""
    return f"{uploads_key(scene_id, upload_id)}/{offset:020d}-{uuid.uuid4().hex[:12]}"


def drop_scene_uploads(database: Database, store: ArtifactStore, scene_id: str) -> None:
    """Remove a scene's unfinished uploads (it was committed: its files are frozen)."""
    with database.write() as s:
        s.execute(delete(Upload).where(Upload.scene_id == scene_id))
    discard(store, [uploads_key(scene_id)])


def expire_uploads(database: Database, store: ArtifactStore, idle_s: float) -> int:
    """Remove uploads that received no chunk for ``idle_s``; how many went."""
    cutoff = datetime.now(UTC) - timedelta(seconds=idle_s)
    with database.write() as s:
        rows = list(s.scalars(select(Upload).where(Upload.updated_at < cutoff)))
        keys = [uploads_key(r.scene_id, r.id) for r in rows]
        for row in rows:
            s.delete(row)
    discard(store, keys)
    return len(keys)
