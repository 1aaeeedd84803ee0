"""Runs recorded before scene.json was relative hold the store's absolute path: fix them.

``scene.json`` is an artifact (a job's run folder is served as is), and a run folder
written before :func:`core.model.run_folder.record_scene` recorded the scene relative to
the run gave out the server's store path. The app rewrites such records when it starts
(relative, as new runs write them) and updates their artifact rows (size, SHA-256), so
upgrading a deployment also stops its old runs from revealing the path.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

from sqlalchemy import update

from api.service.db import Database
from api.service.models import Artifact

log = logging.getLogger("glint.api")


def relativise_scene_records(database: Database, store_root: Path) -> int:
    """Rewrite every absolute ``jobs/*/run/scene.json`` relative; how many were."""
    from core.model.run_folder import SCENE_RECORD, record_scene

    fixed = 0
    for rec in sorted((store_root / "jobs").glob(f"*/run/{SCENE_RECORD}")):
        try:
            where = json.loads(rec.read_text())["scene"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if not isinstance(where, str) or not Path(where).is_absolute():
            continue
        data = record_scene(rec.parent, where).read_bytes()
        with database.write() as s:
            s.execute(
                update(Artifact)
                .where(Artifact.job_id == rec.parent.parent.name, Artifact.name == SCENE_RECORD)
                .values(size=len(data), sha256=hashlib.sha256(data).hexdigest())
            )
        fixed += 1
    if fixed:
        log.info("scene.json of %d run(s) rewritten relative to the run", fixed)
    return fixed
