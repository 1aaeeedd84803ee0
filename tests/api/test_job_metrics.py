"""A job's error-vs-time series over HTTP, its time budget and the time it has left."""

from __future__ import annotations

import pytest

from tests.api.support import TINY_CONFIG, LiveServer, multipart, wait_for

TERMINAL = {"succeeded", "failed", "cancelled"}


def _ready_scene(c, scene) -> str:
    scene_id = c.post("/v1/scenes", json={"name": "metrics"}).json()["id"]
    assert c.post(f"/v1/scenes/{scene_id}/files", files=multipart(scene)).status_code == 201
    assert c.post(f"/v1/scenes/{scene_id}/commit").json()["state"] == "ready"
    return scene_id


@pytest.mark.parametrize("bad", ["soon", "0", "-5m", "9d", 0, -3, "1e400s", "5m5m"])
def test_bad_time_budgets_are_422_naming_the_field(server: LiveServer, scene, bad) -> None:
    with server.client(server.new_key("budget-owner")) as c:
        scene_id = _ready_scene(c, scene)
        before = c.get("/v1/jobs").json()["total"]
        r = c.post(
            "/v1/jobs", json={"scene_id": scene_id, "config": {**TINY_CONFIG, "time_budget": bad}}
        )
        assert r.status_code == 422, r.text
        assert r.headers["content-type"].startswith("application/problem+json")
        assert "time_budget" in r.text
        assert c.get("/v1/jobs").json()["total"] == before  # nothing was created


def test_a_budgeted_job_reports_its_series_and_time_left(server: LiveServer, scene) -> None:
    other = server.new_key("someone-else")
    with server.client(server.new_key("metrics-owner")) as c:
        scene_id = _ready_scene(c, scene)
        config = {**TINY_CONFIG, "time_budget": "1h", "outputs": {"mesh": False}}
        r = c.post("/v1/jobs", json={"scene_id": scene_id, "config": config})
        assert r.status_code == 201, r.text
        job = r.json()
        assert job["time_budget_s"] == 3600.0
        job_id = job["id"]
        job = wait_for(
            lambda: (j := c.get(f"/v1/jobs/{job_id}").json())["state"] in TERMINAL and j,
            timeout=150,
            every=0.2,
        )
        assert job["state"] == "succeeded", job["error"]
        # 20 iterations end it long before the hour: the time left is what remains
        assert 3000 < job["time_left_s"] < 3600
        assert job["metrics"]["geometry"] == "consistency"  # the scene has no ground truth
        assert "depth_normal_consistency_deg" in job["metrics"]

        page = c.get(f"/v1/jobs/{job_id}/metrics").json()
        rows = page["items"]
        assert page["total"] == len(rows) >= 3 and page["offset"] == 0
        assert page["geometry"] == "consistency" and page["time_budget_s"] == 3600.0
        assert rows[0]["iteration"] == 0 and rows[-1]["iteration"] == 20
        assert all("psnr" in r and "wall_time" in r and "eval_seconds" in r for r in rows)
        assert [r["wall_time"] for r in rows] == sorted(r["wall_time"] for r in rows)
        # follow a series: ask again from where the last answer ended
        tail = c.get(f"/v1/jobs/{job_id}/metrics", params={"offset": len(rows) - 1}).json()
        assert tail["items"] == rows[-1:] and tail["total"] == len(rows)
        two = c.get(f"/v1/jobs/{job_id}/metrics", params={"points": 2}).json()["items"]
        assert two == [rows[0], rows[-1]]
        assert c.get(f"/v1/jobs/{job_id}/metrics", params={"points": 0}).status_code == 422
    with server.client(other) as c:  # another owner's job does not exist for them
        r = c.get(f"/v1/jobs/{job_id}/metrics")
        assert r.status_code == 404 and "application/problem+json" in r.headers["content-type"]
