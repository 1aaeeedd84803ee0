"""The embedded default: no Redis configured → the API runs jobs itself (same runner)."""

from __future__ import annotations

import hashlib
from pathlib import Path

from api.service.queue import LocalQueue, make_queue
from tests.api.support import LiveServer, free_port, list_all, make_settings
from tests.worker.flow import ready_scene, submit, wait_state


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
            arts = {a["name"]: a for a in list_all(c, f"/v1/jobs/{job_id}/artifacts")}
            data = c.get(arts["point_cloud.ply"]["url"]).content
            assert hashlib.sha256(data).hexdigest() == arts["point_cloud.ply"]["sha256"]
            assert c.get("/v1/workers").json()["items"] == []  # no Celery workers in this mode
    finally:
        srv.stop()
