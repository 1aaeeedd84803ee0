"""Celery workers on a real Redis, against a real API: success, crashes, restarts,
cancel/resume and duplicate delivery. The database decides; the broker only carries."""

from __future__ import annotations

import hashlib
import json
import re
import time
from collections.abc import Iterator

import httpx
import pytest

from api.service.queue import JobQueue
from tests.api.support import LiveServer, list_all, make_settings, wait_for
from tests.worker.flow import job, ready_scene, submit, wait_iteration, wait_state
from tests.worker.support import RedisServer, Workers, needs_redis

pytestmark = needs_redis


@pytest.fixture(scope="module")
def server(
    tmp_path_factory: pytest.TempPathFactory, redis_server: RedisServer
) -> Iterator[LiveServer]:
    """The API with the default queue choice: Redis configured → the celery backend."""
    settings = make_settings(tmp_path_factory.mktemp("api"), redis_url=redis_server.url)
    srv = LiveServer(settings, None).start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def workers(
    server: LiveServer, redis_server: RedisServer, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Workers]:
    ws = Workers(server, redis_server.url, tmp_path_factory.mktemp("worker-logs"))
    yield ws
    ws.stop_all()


@pytest.fixture(scope="module")
def client(server: LiveServer) -> Iterator[httpx.Client]:
    with server.client(server.new_key("worker-tests")) as c:
        yield c


@pytest.fixture(scope="module")
def scene_id(client: httpx.Client, scene: list[tuple[str, bytes]]) -> str:
    return ready_scene(client, scene)


def _metrics_iterations(server: LiveServer, job_id: str) -> list[int]:
    path = server.settings.store_root / "jobs" / job_id / "run" / "metrics.jsonl"
    return [json.loads(line)["iteration"] for line in path.read_text().splitlines() if line]


def _resumed_from(log: str, job_id: str) -> list[int]:
    return [int(m) for m in re.findall(rf"job {job_id}: resumed from iteration (\d+)", log)]


def test_worker_trains_to_success_and_reports_itself(
    server: LiveServer, workers: Workers, client: httpx.Client, scene_id: str
) -> None:
    assert type(server.app.state.queue).__name__ == "CeleryQueue"
    (a,) = workers.ensure("a")
    listed = wait_for(lambda: list_all(client, "/v1/workers"), timeout=10)
    assert [w["id"] for w in listed] == [a.node]
    assert listed[0]["device"] == "cpu" and listed[0]["busy"] is False

    job_id = submit(client, scene_id, iterations=20)
    busy = wait_for(
        lambda: [w for w in list_all(client, "/v1/workers") if w["current_job"] == job_id],
        timeout=60,
        every=0.05,
    )
    assert busy[0]["id"] == a.node and busy[0]["busy"] is True
    done = wait_state(client, job_id)
    assert done["state"] == "succeeded", done["error"]
    assert done["iteration"] == 20 and done["attempts"] == 1
    assert done["config"]["device"] == "cpu"

    arts = {x["name"]: x for x in list_all(client, f"/v1/jobs/{job_id}/artifacts")}
    assert {"checkpoint.pt", "point_cloud.ply", "metrics.jsonl", "report.md"} <= set(arts)
    ply = client.get(arts["point_cloud.ply"]["url"])
    assert ply.status_code == 200 and ply.content.startswith(b"ply")
    assert hashlib.sha256(ply.content).hexdigest() == arts["point_cloud.ply"]["sha256"]
    wait_for(lambda: list_all(client, "/v1/workers")[0]["busy"] is False, timeout=10)


def test_worker_meshes_jobs_and_reextracts_on_request(
    server: LiveServer, workers: Workers, client: httpx.Client, scene_id: str
) -> None:
    """The job's mesh phase and a re-extraction both run on the Celery worker."""
    import io

    import trimesh

    workers.ensure("a")
    job_id = submit(client, scene_id, iterations=8)
    done = wait_state(client, job_id)
    assert done["state"] == "succeeded", done["error"]
    names = {x["name"] for x in list_all(client, f"/v1/jobs/{job_id}/artifacts")}
    assert {"mesh.ply", "mesh.glb", "mesh.obj", "mesh_preview.png"} <= names
    r = client.post(f"/v1/jobs/{job_id}/meshes", json={"resolution": 32, "color": "radiance"})
    assert r.status_code == 201, r.text
    mesh_job = wait_state(client, r.json()["id"])
    assert mesh_job["state"] == "succeeded", mesh_job["error"]
    assert mesh_job["kind"] == "mesh" and mesh_job["progress"] == 1.0
    assert f"job {mesh_job['id']}: succeeded" in workers.logs()  # the worker ran it
    glb = client.get(f"/v1/jobs/{mesh_job['id']}/artifacts/mesh.glb")
    mesh = trimesh.load(io.BytesIO(glb.content), file_type="glb", force="mesh")
    assert len(mesh.faces) > 20 and mesh.visual.kind == "vertex"


def test_duplicate_messages_train_once(
    server: LiveServer, workers: Workers, client: httpx.Client, scene_id: str
) -> None:
    workers.ensure("a", "b")  # two consumers: duplicates can race each other
    queue: JobQueue = server.app.state.queue
    job_id = submit(client, scene_id, iterations=20)
    queue.enqueue(job_id)
    queue.enqueue(job_id)
    done = wait_state(client, job_id)
    assert done["state"] == "succeeded", done["error"]
    assert done["attempts"] == 1  # claimed once
    # both extra messages were delivered and found nothing to do
    wait_for(lambda: workers.logs().count(f"job {job_id}: not claimable") == 2, timeout=30)
    assert workers.logs().count(f"job {job_id}: succeeded") == 1
    assert _metrics_iterations(server, job_id)[-1] == 20


def test_cancel_stops_fast_keeps_checkpoint_and_resume_finishes(
    server: LiveServer, workers: Workers, client: httpx.Client, scene_id: str
) -> None:
    workers.ensure("a")
    job_id = submit(client, scene_id, iterations=150, checkpoint_every=10)
    wait_iteration(client, job_id, 3)
    t0 = time.monotonic()
    r = client.post(f"/v1/jobs/{job_id}/cancel")
    assert r.status_code == 200, r.text
    cancelled = wait_state(client, job_id, timeout=20)
    took = time.monotonic() - t0
    assert cancelled["state"] == "cancelled" and took < 15
    stopped_at = cancelled["iteration"]
    assert 3 <= stopped_at < 150
    names = {x["name"] for x in list_all(client, f"/v1/jobs/{job_id}/artifacts")}
    assert "checkpoint.pt" in names  # saved at the cancel, not only at a cadence point

    r = client.post(f"/v1/jobs/{job_id}/resume", json={})
    assert r.status_code == 200, r.text
    # run the rest quickly: the resumed job continues at the iteration it stopped
    done = wait_state(client, job_id, timeout=240)
    assert done["state"] == "succeeded", done["error"]
    assert done["iteration"] == 150 and done["attempts"] == 2
    assert _resumed_from(workers.logs(), job_id) == [stopped_at]
    its = _metrics_iterations(server, job_id)
    assert its == sorted(set(its)) and its[-1] == 150


def test_killed_worker_job_resumes_on_another_from_its_checkpoint(
    server: LiveServer, workers: Workers, client: httpx.Client, scene_id: str
) -> None:
    a, b = workers.ensure("a", "b")
    job_id = submit(client, scene_id, iterations=120, checkpoint_every=10)
    wait_iteration(client, job_id, 12)  # the checkpoint at 10 is written
    holder = wait_for(
        lambda: [w["id"] for w in list_all(client, "/v1/workers") if w["current_job"] == job_id]
    )[0]
    victim, survivor = (a, b) if holder == a.node else (b, a)
    victim.kill()
    killed_at = job(client, job_id)["iteration"]

    done = wait_state(client, job_id, timeout=180)
    assert done["state"] == "succeeded", done["error"]
    assert done["iteration"] == 120 and done["attempts"] == 2
    assert "re-queued to resume elsewhere" in survivor.log()  # the reaper noticed
    (resumed,) = _resumed_from(survivor.log(), job_id)
    # Lost at most one checkpoint interval. ``killed_at`` is the API's last progress
    # report, which may lag the worker: the run can have checkpointed past it.
    assert 10 <= resumed < 120 and resumed >= killed_at - 10
    its = _metrics_iterations(server, job_id)
    assert its == sorted(set(its)) and its[-1] == 120  # nothing duplicated, nothing missing
    names = [x["name"] for x in list_all(client, f"/v1/jobs/{job_id}/artifacts")]
    assert len(names) == len(set(names)) and names.count("checkpoint.pt") == 1
    wait_for(lambda: victim.node not in {w["id"] for w in list_all(client, "/v1/workers")}, 10)


def test_job_survives_a_redis_restart(
    server: LiveServer,
    workers: Workers,
    redis_server: RedisServer,
    client: httpx.Client,
    scene_id: str,
) -> None:
    workers.ensure("a", "b")
    job_id = submit(client, scene_id, iterations=100, checkpoint_every=50)
    wait_iteration(client, job_id, 5)
    redis_server.restart(down_s=2.0)
    done = wait_state(client, job_id, timeout=180)
    assert done["state"] == "succeeded", done["error"]
    assert done["iteration"] == 100 and done["attempts"] == 1
    # the workers reconnected: a job sent after the restart runs too
    after = submit(client, scene_id, iterations=20)
    assert wait_state(client, after, timeout=120)["state"] == "succeeded"
