"""The embedded default: no Redis configured → the API runs jobs itself (same runner)."""

from __future__ import annotations

import hashlib
import json
import os
import signal
from pathlib import Path

from api.service.models import Job
from api.service.queue import LocalQueue, make_queue
from tests.api.support import LiveServer, free_port, list_all, make_settings, wait_for
from tests.worker.flow import job, ready_scene, submit, wait_iteration, wait_state


def _runner_pid(srv: LiveServer, job_id: str) -> int:
    """The pid in the job's ``worker`` (``host:pid:thread``)."""
    with srv.database.read() as s:
        worker = s.get(Job, job_id).worker
    return int(worker.split(":")[-2])


def _niceness(pid: int) -> int:
    return int(open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[16])


def test_queue_choice_follows_the_broker_setting(tmp_path: Path) -> None:
    dead = f"redis://127.0.0.1:{free_port()}/0"  # nothing listens there
    local = make_queue(make_settings(tmp_path, redis_url=None))
    assert isinstance(local, LocalQueue)
    local.close()
    celery = make_queue(make_settings(tmp_path, redis_url=dead))  # no connection made yet
    assert type(celery).__name__ == "CeleryQueue"
    celery.close()  # type: ignore[attr-defined]
    explicit = make_queue(make_settings(tmp_path, redis_url=dead, queue_backend="local"))
    assert isinstance(explicit, LocalQueue)
    explicit.close()


def test_embedded_serve_trains_without_any_broker(
    tmp_path: Path, scene: list[tuple[str, bytes]]
) -> None:
    settings = make_settings(tmp_path, redis_url=None)
    srv = LiveServer(settings, None).start()  # the queue `glint serve` would pick
    try:
        assert isinstance(srv.app.state.queue, LocalQueue)
        with srv.client(srv.new_key("embedded")) as c:
            job_id = submit(c, ready_scene(c, scene), iterations=20)
            done = wait_state(c, job_id, timeout=150)
            assert done["state"] == "succeeded", done["error"]
            assert done["iteration"] == 20 and done["attempts"] == 1
            # trained in a process of its own, not on a thread of the API's
            assert _runner_pid(srv, job_id) != os.getpid()
            arts = {a["name"]: a for a in list_all(c, f"/v1/jobs/{job_id}/artifacts")}
            data = c.get(arts["point_cloud.ply"]["url"]).content
            assert hashlib.sha256(data).hexdigest() == arts["point_cloud.ply"]["sha256"]
            assert c.get("/v1/workers").json()["items"] == []  # no Celery workers in this mode
    finally:
        srv.stop()


def test_embedded_job_runs_niced_in_a_child_whose_death_requeues_it(
    tmp_path: Path, scene: list[tuple[str, bytes]]
) -> None:
    """The job trains in a child process at a lower priority; kill -9 of that child is
    a dead runner: the job says so, is requeued at once and resumes from its checkpoint."""
    settings = make_settings(tmp_path, redis_url=None, embedded_job_nice=7)
    srv = LiveServer(settings, None).start()
    try:
        with srv.client(srv.new_key("embedded")) as c:
            # long enough that it cannot finish between the iteration seen and the kill
            job_id = submit(c, ready_scene(c, scene), iterations=400, outputs={"mesh": False})
            wait_iteration(c, job_id, 12)
            pid = _runner_pid(srv, job_id)
            assert pid != os.getpid()
            assert _niceness(pid) == min(_niceness(os.getpid()) + 7, 19)
            os.kill(pid, signal.SIGKILL)
            seen = wait_for(lambda: "stopped heartbeating" in (job(c, job_id)["error"] or ""), 10)
            assert seen
            done = wait_state(c, job_id, timeout=90)
            assert done["state"] == "succeeded", done["error"]
            assert done["iteration"] == 400 and done["attempts"] == 2
            assert _runner_pid(srv, job_id) not in (pid, os.getpid())
    finally:
        srv.stop()
    metrics = settings.store_root / "jobs" / job_id / "run" / "metrics.jsonl"
    its = [json.loads(line)["iteration"] for line in metrics.read_text().splitlines() if line]
    assert its == sorted(set(its)) and its[-1] == 400
