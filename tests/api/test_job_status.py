"""``GET /v1/jobs/{id}`` reads the key and the job on a path of its own (one read, plain
columns; issue 25's latency work): it must answer exactly like every other route."""

from __future__ import annotations

from datetime import UTC, datetime

import httpx

from api.auth import create_key
from api.schemas import JobOut
from api.service.models import ApiKey, Job, JobState, Scene, SceneState, new_id
from tests.api.support import LiveServer


def _running_job(server: LiveServer, owner: str) -> str:
    """A running job with every kind of column filled (JSON, floats, times), as rows."""
    now = datetime.now(UTC)
    job_id = new_id("job")
    with server.database.write() as s:
        scene = Scene(id=new_id("scn"), owner=owner, name="status", state=SceneState.READY)
        s.add(scene)
        s.flush()
        s.add(
            Job(
                id=job_id,
                owner=owner,
                scene_id=scene.id,
                state=JobState.RUNNING,
                config={"iterations": 300, "time_budget": 90.0},
                total_iterations=300,
                iteration=120,
                phase="geometry",
                n_gaussians=4321,
                loss=0.0123,
                metrics={"psnr": 27.5, "time_left": 41.0},
                plan={"envmap": True},
                stage={"name": "mesh", "step": "integrate", "done": 3, "total": 24},
                elapsed_s=12.5,
                eta_s=18.75,
                version=7,
                attempts=1,
                started_at=now,
            )
        )
    return job_id


def _key(server: LiveServer, owner: str, scope: str = "admin") -> tuple[str, str]:
    with server.database.write() as s:
        row, key = create_key(s, owner, scope=scope)
    return row.id, key


def _status(r: httpx.Response, slug: str) -> int:
    assert r.headers["content-type"] == "application/problem+json", r.text
    assert r.json()["type"] == f"urn:glint:problem:{slug}", r.text
    return r.status_code


def test_status_answers_like_the_list(any_server: LiveServer) -> None:
    owner = f"status-{any_server.port}"
    job_id = _running_job(any_server, owner)
    key_id, key = _key(any_server, owner, scope="read")
    with any_server.client(key) as c:
        r = c.get(f"/v1/jobs/{job_id}")
        assert r.status_code == 200 and r.headers["content-type"] == "application/json"
        assert r.headers["etag"] == f'W/"{job_id}-7"' and r.headers["cache-control"] == "no-cache"
        body = r.json()
        assert JobOut.model_validate(body).model_dump(mode="json") == body
        listed = [j for j in c.get("/v1/jobs").json()["items"] if j["id"] == job_id]
        assert listed == [body]
        assert body["progress"] == 0.4 and body["time_budget_s"] == 90.0
        assert body["time_left_s"] == 41.0 and body["started_at"].endswith("Z")
        same = c.get(f"/v1/jobs/{job_id}", headers={"If-None-Match": r.headers["etag"]})
        assert same.status_code == 304 and same.headers["etag"] == r.headers["etag"]
    with any_server.database.read() as s:  # the poll counts as the key's use
        assert s.get(ApiKey, key_id).last_used_at is not None


def test_status_refusals_keep_their_order(any_server: LiveServer) -> None:
    owner = f"refusals-{any_server.port}"
    job_id = _running_job(any_server, owner)
    key_id, key = _key(any_server, owner)
    long_id = "j" * 41
    with any_server.client(None) as anon:
        assert _status(anon.get(f"/v1/jobs/{job_id}"), "unauthorized") == 401
    with any_server.client("glk_not-a-key") as bad:  # the key before the path's checks
        assert _status(bad.get(f"/v1/jobs/{long_id}"), "unauthorized") == 401
    with any_server.client(key) as c:
        assert _status(c.get(f"/v1/jobs/{long_id}"), "validation-error") == 422
        assert _status(c.get("/v1/jobs/job_missing"), "not-found") == 404
        with any_server.client(_key(any_server, "someone-else")[1]) as other:
            assert _status(other.get(f"/v1/jobs/{job_id}"), "not-found") == 404
        assert c.get(f"/v1/jobs/{job_id}").status_code == 200
        with any_server.database.write() as s:  # revoked elsewhere: refused at once
            s.get(ApiKey, key_id).revoked_at = datetime.now(UTC)
        assert _status(c.get(f"/v1/jobs/{job_id}"), "unauthorized") == 401
