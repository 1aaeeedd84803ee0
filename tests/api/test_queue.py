"""The embedded queue (``GLINT_QUEUE_BACKEND=local``) and backend selection."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

from api.service.db import Database
from api.service.migrate import upgrade
from api.service.models import Job, JobState, Scene, SceneState, new_id
from api.service.queue import LocalQueue, make_queue, queue_kind
from api.service.settings import Settings
from tests.api.support import (
    TINY_CONFIG,
    LiveServer,
    make_settings,
    multipart,
    wait_for,
)


def test_backend_selection(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    assert isinstance(make_queue(settings), LocalQueue)
    assert queue_kind(settings) == "local"
    with_broker = settings.model_copy(update={"redis_url": "redis://127.0.0.1:1/0"})
    assert queue_kind(with_broker) == "celery"
    forced = with_broker.model_copy(update={"queue_backend": "local"})
    assert queue_kind(forced) == "local" and isinstance(make_queue(forced), LocalQueue)
    # the queue is a setting, not a module path: anything else is refused by name
    with pytest.raises(ValidationError, match="queue_backend"):
        Settings(queue_backend="tests.api.support:RecordingQueue")
    with pytest.raises(ValueError, match="unknown queue backend"):
        make_queue(settings.model_copy(update={"queue_backend": "carrier-pigeon"}))


def test_local_queue_restarts_orphans_after_a_crash(tmp_path: Path) -> None:
    """A job left 'running' by a dead process is re-queued and run by the new one.

    Its scene has no files in the store, so the rerun fails fast at loading: enough to
    see the embedded queue pick it up, run it and record the outcome.
    """
    settings = make_settings(tmp_path)
    db = Database(settings.db_url)
    upgrade(db.engine)
    sid, orphan, waiting = new_id("scn"), new_id("job"), new_id("job")
    with db.write() as s:
        s.add(Scene(id=sid, owner="o", name="s", state=SceneState.READY))
        s.flush()
        for jid, state in ((orphan, JobState.RUNNING), (waiting, JobState.QUEUED)):
            s.add(
                Job(
                    id=jid,
                    owner="o",
                    scene_id=sid,
                    config={"iterations": 5},
                    total_iterations=5,
                    state=state,
                    lease="dead",
                    attempts=1,
                )
            )
    db.dispose()

    srv = LiveServer(settings, queue=None).start()  # the app builds its LocalQueue
    try:
        assert isinstance(srv.app.state.queue, LocalQueue)

        def done() -> bool:
            with srv.database.read() as s:
                states = [s.get(Job, j).state for j in (orphan, waiting)]
            return all(st == JobState.FAILED for st in states)

        wait_for(done, timeout=60)
        with srv.database.read() as s:
            job = s.get(Job, orphan)
            assert job.attempts == 2 and "does not exist" in job.error
    finally:
        srv.stop()


def test_shutdown_requeues_a_running_job_and_restart_resumes_it(tmp_path: Path, scene) -> None:
    """Stopping ``glint serve`` mid-training checkpoints the job and puts it back in the
    queue (not 'cancelled': nobody asked); the next start resumes it to the end."""
    settings = make_settings(tmp_path)
    srv = LiveServer(settings, queue=None).start()
    try:
        key = srv.new_key("restarter")
        with srv.client(key) as c:
            sid = c.post("/v1/scenes", json={"name": "s"}).json()["id"]
            c.post(f"/v1/scenes/{sid}/files", files=multipart(scene))
            assert c.post(f"/v1/scenes/{sid}/commit").status_code == 200
            config = {**TINY_CONFIG, "iterations": 150, "checkpoint_every": 1000}
            job_id = c.post("/v1/jobs", json={"scene_id": sid, "config": config}).json()["id"]
            wait_for(lambda: c.get(f"/v1/jobs/{job_id}").json()["iteration"] >= 2, every=0.05)
    finally:
        srv.stop()  # lifespan shutdown: LocalQueue.close() stops the trainer
    db = Database(settings.db_url)
    with db.read() as s:
        job = s.get(Job, job_id)
        assert job.state == JobState.QUEUED and job.lease is None
        stopped_at = job.iteration
    db.dispose()
    assert 2 <= stopped_at < 150
    assert (settings.store_root / "jobs" / job_id / "run" / "checkpoint.pt").is_file()

    srv = LiveServer(settings, queue=None).start()
    try:
        with srv.client(key) as c:
            done = wait_for(
                lambda: (j := c.get(f"/v1/jobs/{job_id}").json())["state"] == "succeeded" and j,
                timeout=150,
            )
        assert done["iteration"] == 150 and done["attempts"] == 2
    finally:
        srv.stop()


def test_importing_the_service_does_not_import_torch() -> None:
    """Workers fork after importing the task code; CUDA must not be initialised before."""
    code = (
        "import sys, api.main, api.service.runner, api.service.queue, api.cli; "
        "sys.exit('torch' in sys.modules)"
    )
    repo = Path(__file__).resolve().parents[2]
    assert subprocess.run([sys.executable, "-c", code], cwd=repo).returncode == 0
