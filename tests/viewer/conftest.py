"""One real API server with one tiny trained job, shared by every viewer test.

The job goes through the real service path (scene upload, validation, training by
the real runner on a thread) so the viewer is tested against a genuine run folder;
training is kept to a few iterations on a 24×24 scene to stay cheap.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from tests.api.support import (
    TINY_CONFIG,
    LiveServer,
    ThreadQueue,
    make_settings,
    multipart,
    scene_files,
    wait_for,
)

VIEWER_CONFIG = {
    **TINY_CONFIG,
    "iterations": 12,
    "checkpoint_every": 6,
    "eval": {"every": 6, "views": 1},
}


@dataclass
class TrainedJob:
    server: LiveServer
    key: str
    job_id: str

    @property
    def ws_base(self) -> str:
        return self.server.url.replace("http://", "ws://") + f"/v1/jobs/{self.job_id}/viewer/ws"

    def token(self) -> str:
        with self.server.client(self.key) as c:
            r = c.post(f"/v1/jobs/{self.job_id}/viewer-token")
            assert r.status_code == 200, r.text
            return r.json()["token"]

    @property
    def run_dir(self) -> Path:
        return self.server.settings.store_root / "jobs" / self.job_id / "run"


@pytest.fixture(scope="session")
def viewer_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    settings = make_settings(tmp_path_factory.mktemp("viewer-server"))
    srv = LiveServer(settings, ThreadQueue(settings)).start()
    yield srv
    srv.queue.join(60)
    srv.stop()


@pytest.fixture(scope="session")
def trained_job(viewer_server: LiveServer, tmp_path_factory: pytest.TempPathFactory) -> TrainedJob:
    """A succeeded job trained on a 24×24 glossy sphere (6 train + 2 test views)."""
    from core.scene.synthetic import write_synthetic_scene

    scene_dir = write_synthetic_scene(
        tmp_path_factory.mktemp("viewer-scene"), "sphere", "glossy", n_train=6, n_test=2, size=24
    )
    srv = viewer_server
    key = srv.new_key("viewer-owner")
    with srv.client(key) as c:
        scene_id = c.post("/v1/scenes", json={"name": "viewer sphere"}).json()["id"]
        r = c.post(f"/v1/scenes/{scene_id}/files", files=multipart(scene_files(scene_dir)))
        assert r.status_code == 201, r.text
        assert c.post(f"/v1/scenes/{scene_id}/commit").json()["state"] == "ready"
        r = c.post("/v1/jobs", json={"scene_id": scene_id, "config": VIEWER_CONFIG})
        assert r.status_code == 201, r.text
        job_id = r.json()["id"]

        def done() -> dict | None:
            j = c.get(f"/v1/jobs/{job_id}").json()
            return j if j["state"] in ("succeeded", "failed", "cancelled") else None

        job = wait_for(done, timeout=150, every=0.2)
        assert job["state"] == "succeeded", job["error"]
    return TrainedJob(srv, key, job_id)


@pytest.fixture
def http(trained_job: TrainedJob) -> Iterator[httpx.Client]:
    with trained_job.server.client(trained_job.key) as c:
        yield c
