"""Jobs over HTTP: cancel (queued and running), resume from the checkpoint, failure,
the event stream, list filters and pagination, ETags on polling."""

from __future__ import annotations

import json
import shutil
import threading

import httpx
import pytest

from tests.api.support import TINY_CONFIG, LiveServer, job_events, list_all, multipart, wait_for

TERMINAL = {"succeeded", "failed", "cancelled"}
# long enough that the cancel lands mid-run even on a fast machine
LONGER = {**TINY_CONFIG, "iterations": 200, "checkpoint_every": 1000}


@pytest.fixture
def ready_scene(client: httpx.Client, scene) -> str:
    sid = client.post("/v1/scenes", json={"name": "jobs"}).json()["id"]
    assert client.post(f"/v1/scenes/{sid}/files", files=multipart(scene)).status_code == 201
    assert client.post(f"/v1/scenes/{sid}/commit").status_code == 200
    return sid


def _job(client: httpx.Client, job_id: str) -> dict:
    r = client.get(f"/v1/jobs/{job_id}")
    assert r.status_code == 200, r.text
    return r.json()


def _wait_terminal(client: httpx.Client, job_id: str) -> dict:
    return wait_for(
        lambda: (j := _job(client, job_id))["state"] in TERMINAL and j, timeout=150, every=0.2
    )


def test_cancel_queued_job_is_immediate(server: LiveServer, client, ready_scene) -> None:
    server.queue.hold()
    try:
        job = client.post("/v1/jobs", json={"scene_id": ready_scene, "config": TINY_CONFIG}).json()
        assert job["state"] == "queued" and job["progress"] == 0.0
        r = client.post(f"/v1/jobs/{job['id']}/cancel")
        assert r.status_code == 200
        assert r.json()["state"] == "cancelled" and r.json()["finished_at"]
    finally:
        server.queue.release()
    server.queue.join(30)
    assert server.queue.results[job["id"]] == [None]  # the runner found nothing to claim
    assert _job(client, job["id"])["state"] == "cancelled"
    assert client.post(f"/v1/jobs/{job['id']}/cancel").status_code == 409


def test_cancel_running_then_resume_continues(server: LiveServer, client, ready_scene) -> None:
    job_id = client.post("/v1/jobs", json={"scene_id": ready_scene, "config": LONGER}).json()["id"]
    wait_for(lambda: _job(client, job_id)["iteration"] >= 3, timeout=120, every=0.1)
    r = client.post(f"/v1/jobs/{job_id}/cancel")
    assert r.status_code == 200, r.text
    assert r.json()["cancel_requested"] is True or r.json()["state"] == "cancelled"
    stopped = _wait_terminal(client, job_id)
    assert stopped["state"] == "cancelled", stopped["error"]
    at = stopped["iteration"]
    assert 3 <= at < 200
    names = [a["name"] for a in list_all(client, f"/v1/jobs/{job_id}/artifacts")]
    assert "checkpoint.pt" in names  # saved on stop: what resume continues from

    r = client.post(f"/v1/jobs/{job_id}/resume")
    assert r.status_code == 200 and r.json()["state"] == "queued"
    assert r.json()["cancel_requested"] is False
    events = job_events(client, job_id)
    assert events[-1] == ("end", {"state": "succeeded"})
    running = [e for kind, e in events if kind == "job" and e["state"] == "running"]
    assert running, "the stream showed the job running"
    assert all(e["iteration"] >= at for e in running), "resume restarted from scratch"
    versions = [e["version"] for kind, e in events if kind == "job"]
    assert versions == sorted(set(versions))
    done = _job(client, job_id)
    assert done["state"] == "succeeded" and done["iteration"] == 200
    assert done["attempts"] == 2
    assert client.post(f"/v1/jobs/{job_id}/resume").status_code == 409
    assert client.post(f"/v1/jobs/{job_id}/cancel").status_code == 409
    # a duplicate delivery of a finished job is a no-op
    server.queue.enqueue(job_id)
    server.queue.join(30)
    assert server.queue.results[job_id][-1] is None
    assert _job(client, job_id)["version"] == done["version"]


def test_failed_job_reports_error_and_can_be_resumed(
    server: LiveServer, client, ready_scene
) -> None:
    # the store loses the scene behind the API's back: the runner cannot load it
    files = server.settings.store_root / "scenes" / ready_scene / "files"
    shutil.rmtree(files)
    job_id = client.post("/v1/jobs", json={"scene_id": ready_scene, "config": TINY_CONFIG}).json()[
        "id"
    ]
    job = _wait_terminal(client, job_id)
    assert job["state"] == "failed"
    assert "does not exist" in job["error"]
    assert str(server.settings.store_root) not in job["error"]
    assert job["finished_at"] is not None
    r = client.post(f"/v1/jobs/{job_id}/resume")
    assert r.status_code == 200 and r.json()["state"] == "queued" and r.json()["error"] is None
    assert _wait_terminal(client, job_id)["state"] == "failed"
    assert client.delete(f"/v1/jobs/{job_id}").status_code == 204
    assert client.get(f"/v1/jobs/{job_id}").status_code == 404
    assert not (server.settings.store_root / "jobs" / job_id).exists()


def test_list_filters_and_pagination(server: LiveServer, client, ready_scene, scene) -> None:
    server.queue.hold()
    try:
        ids = [
            client.post("/v1/jobs", json={"scene_id": ready_scene}).json()["id"] for _ in range(3)
        ]
        client.post(f"/v1/jobs/{ids[0]}/cancel")
        queued = client.get("/v1/jobs", params={"state": "queued"}).json()
        assert queued["total"] == 2 and {j["id"] for j in queued["items"]} == set(ids[1:])
        both = client.get("/v1/jobs", params=[("state", "queued"), ("state", "cancelled")]).json()
        assert both["total"] == 3
        page = client.get("/v1/jobs", params={"limit": 2, "offset": 0}).json()
        rest = client.get("/v1/jobs", params={"limit": 2, "offset": 2}).json()
        assert page["total"] == rest["total"] == 3
        assert [j["id"] for j in page["items"] + rest["items"]] == ids[::-1]  # newest first
        other = client.post("/v1/scenes", json={"name": "other"}).json()["id"]
        assert client.get("/v1/jobs", params={"scene_id": other}).json()["total"] == 0
        assert client.get("/v1/jobs", params={"scene_id": ready_scene}).json()["total"] == 3
        # a job in use keeps its scene
        assert client.delete(f"/v1/scenes/{ready_scene}").status_code == 409
        assert client.delete(f"/v1/jobs/{ids[1]}").status_code == 409  # queued: cancel first
        for job_id in ids[1:]:
            assert client.post(f"/v1/jobs/{job_id}/cancel").json()["state"] == "cancelled"
    finally:
        server.queue.release()
    server.queue.join(30)


def test_job_etag_revalidation(server: LiveServer, client, ready_scene) -> None:
    server.queue.hold()
    try:
        job_id = client.post("/v1/jobs", json={"scene_id": ready_scene}).json()["id"]
        r = client.get(f"/v1/jobs/{job_id}")
        etag = r.headers["etag"]
        assert client.get(f"/v1/jobs/{job_id}", headers={"If-None-Match": etag}).status_code == 304
        client.post(f"/v1/jobs/{job_id}/cancel")
        r2 = client.get(f"/v1/jobs/{job_id}", headers={"If-None-Match": etag})
        assert r2.status_code == 200 and r2.headers["etag"] != etag
    finally:
        server.queue.release()


def test_owners_do_not_see_each_other(server: LiveServer, client, ready_scene) -> None:
    with server.client(server.new_key("stranger")) as other:
        assert other.get("/v1/scenes").json()["total"] == 0
        assert other.get(f"/v1/scenes/{ready_scene}").status_code == 404
        assert other.get(f"/v1/scenes/{ready_scene}/files").status_code == 404
        assert other.post(f"/v1/scenes/{ready_scene}/commit").status_code == 404
    assert client.get("/v1/scenes").json()["total"] == 1


def test_event_stream_honours_last_event_id(server: LiveServer, client, ready_scene) -> None:
    """A reconnecting client that saw the current version gets only what comes after."""
    server.queue.hold()
    try:
        job = client.post("/v1/jobs", json={"scene_id": ready_scene}).json()
        timer = threading.Timer(0.5, lambda: client.post(f"/v1/jobs/{job['id']}/cancel"))
        timer.start()
        events, kind, data = [], None, []
        headers = {"Last-Event-ID": str(job["version"])}
        with client.stream("GET", f"/v1/jobs/{job['id']}/events", headers=headers) as r:
            for line in r.iter_lines():
                if line.startswith("event: "):
                    kind = line[7:]
                elif line.startswith("data: "):
                    data.append(line[6:])
                elif not line and kind:
                    events.append((kind, json.loads("".join(data))))
                    kind, data = None, []
        timer.join()
    finally:
        server.queue.release()
    assert [k for k, _ in events] == ["job", "end"]
    assert events[0][1]["state"] == "cancelled" and events[0][1]["version"] > job["version"]
