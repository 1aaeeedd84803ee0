"""The periodic sweep of the artifact store: what no row accounts for goes.

Objects are written before their rows and deleted after them (write, then commit the
row; delete the row, then the objects), so a crash, or a store that was down when a
scene or job was deleted, can leave objects behind that nothing lists. Every
``store_sweep_s`` the API removes

* ``scenes/{id}/...`` and ``jobs/{id}/...`` whose scene or job row is gone, once
  nothing under them changed for ``ORPHAN_GRACE_S`` (a row is committed before its
  first object, so a missing row means a deleted one; the grace only guards clocks);
* abandoned writes older than a day: multipart uploads an API process started and never
  completed or aborted (it died mid-upload), or staging files of a directory store.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any

from sqlalchemy import select

from api.service.chunk_uploads import expire_uploads
from api.service.db import Database
from api.service.idempotency import forget_expired
from api.service.models import Job, Scene
from api.service.settings import Settings
from api.service.store import ArtifactStore, StoreUnavailableError, job_key, scene_key

log = logging.getLogger("glint.sweeper")

ORPHAN_GRACE_S = 900.0
ABANDONED_AFTER_S = 24 * 3600.0
UPLOAD_IDLE_S: float = Settings.model_fields["upload_expire_s"].default
IDEMPOTENCY_TTL_S: float = Settings.model_fields["idempotency_ttl_s"].default
_ID_BATCH = 500


@dataclass
class Swept:
    scenes: int = 0
    jobs: int = 0
    uploads: int = 0
    resumable: int = 0
    idempotency_keys: int = 0


def _known(database: Database, column: Any, ids: list[str]) -> set[str]:
    out: set[str] = set()
    with database.read() as s:
        for i in range(0, len(ids), _ID_BATCH):
            out |= set(s.scalars(select(column).where(column.in_(ids[i : i + _ID_BATCH]))))
    return out


def _quiet_since(store: ArtifactStore, prefix: str, cutoff: float) -> bool:
    """Nothing under ``prefix`` was written after ``cutoff`` (epoch seconds)."""
    return all(o.mtime < cutoff for o in store.list(prefix))


def sweep(
    database: Database,
    store: ArtifactStore,
    *,
    grace_s: float = ORPHAN_GRACE_S,
    abandoned_after_s: float = ABANDONED_AFTER_S,
    upload_idle_s: float = UPLOAD_IDLE_S,
    idempotency_ttl_s: float = IDEMPOTENCY_TTL_S,
) -> Swept:
    """One pass: orphaned scene and job prefixes, abandoned uploads (store writes and
    resumable uploads nobody finished), expired Idempotency-Keys; what went."""
    out = Swept()
    out.resumable = expire_uploads(database, store, upload_idle_s)
    out.idempotency_keys = forget_expired(database, idempotency_ttl_s)
    cutoff = time.time() - grace_s
    for kind, column, key in (("scenes", Scene.id, scene_key), ("jobs", Job.id, job_key)):
        ids = store.children(kind)
        for orphan in sorted(set(ids) - _known(database, column, ids)):
            if _quiet_since(store, key(orphan), cutoff):
                store.delete(key(orphan))
                setattr(out, kind, getattr(out, kind) + 1)
                log.info("sweep: removed %s/%s (no %s row)", kind, orphan, kind[:-1])
    out.uploads = store.sweep_abandoned(abandoned_after_s)
    if out.uploads:
        log.info("sweep: removed %d abandoned upload(s)", out.uploads)
    return out


class Sweeper:
    """:func:`sweep` every ``period_s`` on a thread of its own (the API runs one)."""

    def __init__(
        self,
        database: Database,
        store: ArtifactStore,
        period_s: float,
        grace_s: float = ORPHAN_GRACE_S,
        upload_idle_s: float = UPLOAD_IDLE_S,
        idempotency_ttl_s: float = IDEMPOTENCY_TTL_S,
    ) -> None:
        self.database, self.store, self.period_s, self.grace_s = database, store, period_s, grace_s
        self.upload_idle_s, self.idempotency_ttl_s = upload_idle_s, idempotency_ttl_s
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="glint-sweeper", daemon=True)

    def start(self) -> Sweeper:
        self._thread.start()
        return self

    def _loop(self) -> None:
        while not self._closed.wait(self.period_s):
            try:
                sweep(
                    self.database,
                    self.store,
                    grace_s=self.grace_s,
                    upload_idle_s=self.upload_idle_s,
                    idempotency_ttl_s=self.idempotency_ttl_s,
                )
            except StoreUnavailableError as exc:
                log.warning("sweep skipped: %s", exc)
            except Exception:
                log.warning("sweep failed", exc_info=True)

    def close(self) -> None:
        self._closed.set()
        if self._thread.is_alive():
            self._thread.join(10)
