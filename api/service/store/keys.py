"""Store keys: the layout API and workers share, and the check every key passes.

::

    scenes/{scene_id}/files/...   uploaded scene files (the scene folder)
    jobs/{job_id}/run/...         the run folder train_scene writes into
    jobs/{job_id}/scene/...       the COLMAP scene the job's sfm phase made (images-only scenes)
    tmp/...                       staging (directory store only)
"""

from __future__ import annotations

from api.service.store.base import StoreError


def scene_files_key(scene_id: str) -> str:
    return f"scenes/{scene_id}/files"


def scene_key(scene_id: str) -> str:
    return f"scenes/{scene_id}"


def job_run_key(job_id: str) -> str:
    return f"jobs/{job_id}/run"


def job_scene_key(job_id: str) -> str:
    """The scene a job's ``sfm`` phase recovered from plain photos (deleted with the job)."""
    return f"jobs/{job_id}/scene"


def job_key(job_id: str) -> str:
    return f"jobs/{job_id}"


def check_key(key: str) -> str:
    """``key`` if it is a clean relative POSIX path, else :class:`StoreError`."""
    if not key or "\\" in key or "\x00" in key or key.startswith("/"):
        raise StoreError(f"invalid store key {key!r}")
    if any(p in ("", ".", "..") for p in key.split("/")):
        raise StoreError(f"invalid store key {key!r}")
    return key
