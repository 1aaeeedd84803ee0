"""Client-side steps shared by the worker tests: upload a scene, submit, wait."""

from __future__ import annotations

from typing import Any

import httpx

from tests.api.support import TINY_CONFIG, multipart, wait_for

TERMINAL = {"succeeded", "failed", "cancelled"}


def ready_scene(c: httpx.Client, scene: list[tuple[str, bytes]]) -> str:
    r = c.post("/v1/scenes", json={"name": "sphere"})
    assert r.status_code == 201, r.text
    scene_id = r.json()["id"]
    r = c.post(f"/v1/scenes/{scene_id}/files", files=multipart(scene))
    assert r.status_code == 201, r.text
    r = c.post(f"/v1/scenes/{scene_id}/commit")
    assert r.status_code == 200 and r.json()["state"] == "ready", r.text
    return scene_id


def submit(c: httpx.Client, scene_id: str, **config: Any) -> str:
    cfg = {**TINY_CONFIG, "eval": {"every": 1000, "views": 1}, **config}
    r = c.post("/v1/jobs", json={"scene_id": scene_id, "config": cfg})
    assert r.status_code == 201, r.text
    return str(r.json()["id"])


def job(c: httpx.Client, job_id: str) -> dict[str, Any]:
    r = c.get(f"/v1/jobs/{job_id}")
    assert r.status_code == 200, r.text
    return dict(r.json())


def wait_state(
    c: httpx.Client, job_id: str, states: set[str] = TERMINAL, timeout: float = 120.0
) -> dict[str, Any]:
    return dict(wait_for(lambda: (j := job(c, job_id))["state"] in states and j, timeout, 0.1))


def wait_iteration(c: httpx.Client, job_id: str, at_least: int, timeout: float = 120.0) -> dict:
    def reached() -> dict | None:
        j = job(c, job_id)
        assert j["state"] in ("queued", "running"), j
        return j if j["state"] == "running" and j["iteration"] >= at_least else None

    return dict(wait_for(reached, timeout, 0.05))
