"""The artifact store: one interface (:mod:`.base`), a directory (:mod:`.local`) or an
S3-compatible bucket (:mod:`.s3`), chosen by :func:`.factory.make_store` from settings."""

from api.service.store.base import (
    ArtifactStore,
    PendingWrite,
    StoredObject,
    StoreError,
    StoreUnavailableError,
    WriteResult,
    is_staging,
)
from api.service.store.factory import CHECK_TIMEOUT_S, make_store
from api.service.store.keys import (
    check_key,
    job_key,
    job_run_key,
    job_scene_key,
    scene_files_key,
    scene_key,
)
from api.service.store.local import LocalStore
from api.service.store.probe import StoreProbe
from api.service.store.retry import retrying

__all__ = [
    "CHECK_TIMEOUT_S",
    "ArtifactStore",
    "LocalStore",
    "PendingWrite",
    "StoreError",
    "StoreProbe",
    "StoreUnavailableError",
    "StoredObject",
    "WriteResult",
    "check_key",
    "is_staging",
    "job_key",
    "job_run_key",
    "job_scene_key",
    "make_store",
    "retrying",
    "scene_files_key",
    "scene_key",
]
