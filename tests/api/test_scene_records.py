"""Old runs' scene.json (the store's absolute path) is rewritten relative when the app starts."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from api.service.db import Database
from api.service.migrate import upgrade
from api.service.models import Artifact, Job, Scene, SceneState, new_id
from api.service.scene_records import relativise_scene_records
from api.service.store import job_run_key, scene_files_key
from core.model.run_folder import find_run_scene
from tests.api.support import LiveServer, RecordingQueue, make_settings


def test_absolute_scene_records_are_rewritten_at_start(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    db = Database(settings.db_url)
    upgrade(db.engine)
    sid, jid = new_id("scn"), new_id("job")
    scene_dir = settings.store_root / scene_files_key(sid)
    run = settings.store_root / job_run_key(jid)
    scene_dir.mkdir(parents=True)
    run.mkdir(parents=True)
    old = json.dumps({"scene": str(scene_dir.resolve())}).encode()
    (run / "scene.json").write_bytes(old)
    with db.write() as s:
        s.add(Scene(id=sid, owner="t", name="s", state=SceneState.READY))
        s.flush()
        s.add(Job(id=jid, owner="t", scene_id=sid, config={}, total_iterations=1))
        s.flush()
        sha = hashlib.sha256(old).hexdigest()
        s.add(Artifact(job_id=jid, name="scene.json", size=len(old), sha256=sha, content_type="j"))
    db.dispose()

    srv = LiveServer(settings, RecordingQueue()).start()  # its start-up does the rewrite
    try:
        new = (run / "scene.json").read_bytes()
        assert str(tmp_path).encode() not in new
        assert find_run_scene(run) == scene_dir.resolve()
        with srv.database.read() as s:
            art = s.query(Artifact).filter_by(job_id=jid, name="scene.json").one()
            assert (art.size, art.sha256) == (len(new), hashlib.sha256(new).hexdigest())
        assert relativise_scene_records(srv.database, settings.store_root) == 0  # done once
    finally:
        srv.stop()
        srv.database.dispose()
