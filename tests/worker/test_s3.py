"""API and Celery workers that share nothing but the database and an S3 bucket (a real S3
endpoint: moto's server, credentials checked): the whole trip from upload to mesh, an
endpoint that stops answering mid-job, and a job resumed on another host from the
checkpoint in the bucket.

Each process has a data folder of its own (API, worker a, worker b); the only other
thing they share is the SQLite file standing in for PostgreSQL, in a folder of its own.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.api.support import LiveServer, list_all, make_settings, wait_for
from tests.photo_capture import VIEWS, photo_files
from tests.s3_server import S3Server
from tests.worker.flow import job, ready_scene, submit, wait_state
from tests.worker.support import RedisServer, Workers, needs_redis

pytestmark = needs_redis


@pytest.fixture(scope="module")
def s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    srv = S3Server(tmp_path_factory.mktemp("moto")).start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def bucket(s3: S3Server) -> str:
    return s3.bucket()


@pytest.fixture(scope="module")
def roots(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return {name: tmp_path_factory.mktemp(name) for name in ("db", "api", "worker-a", "worker-b")}


@pytest.fixture(scope="module")
def server(
    s3: S3Server, bucket: str, redis_server: RedisServer, roots: dict[str, Path]
) -> Iterator[LiveServer]:
    settings = make_settings(
        roots["api"],
        f"sqlite:///{roots['db'] / 'glint.db'}",
        redis_url=redis_server.url,
        store_sweep_s=0,
        **s3.settings(bucket),
    )
    srv = LiveServer(settings, None).start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def workers(
    server: LiveServer,
    s3: S3Server,
    bucket: str,
    redis_server: RedisServer,
    roots: dict[str, Path],
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[Workers]:
    ws = Workers(server, redis_server.url, tmp_path_factory.mktemp("logs"), **s3.env(bucket))
    for name in ("a", "b"):  # each on its own folder: nothing of the API's is in reach
        own = roots[f"worker-{name}"]
        ws.start(name, GLINT_DATA_DIR=str(own), GLINT_STORE_DIR=str(own / "unused-store"))
    for w in ws.procs.values():
        w.wait_ready()
    yield ws
    ws.stop_all()


@pytest.fixture(scope="module")
def client(server: LiveServer) -> Iterator[httpx.Client]:
    with server.client(server.new_key("s3-tests")) as c:
        yield c


def _files(root: Path) -> list[str]:
    """Every file under ``root``; folders a worker removes during the walk are skipped."""
    return sorted(
        (Path(d) / f).relative_to(root).as_posix() for d, _, fs in os.walk(root) for f in fs
    )


def _dropped(root: Path, job_id: str) -> bool:
    """The worker has dropped its local copy of the job's folders. It drops them right
    after recording the job's end, so a test that saw the end may still see them."""
    return not [f for f in _files(root) if f"jobs/{job_id}" in f]


def _viewer_frame(server: LiveServer, client: httpx.Client, job_id: str) -> dict:
    """Open the job in the viewer (its checkpoint comes from the bucket) and get a frame."""
    from websockets.sync.client import connect

    from viewer_web.protocol import unpack_frame

    token = client.post(f"/v1/jobs/{job_id}/viewer-token").json()["token"]
    url = server.url.replace("http://", "ws://") + f"/v1/jobs/{job_id}/viewer/ws?token={token}"
    with connect(url, open_timeout=20, max_size=None) as ws:
        hello = json.loads(ws.recv(timeout=60))
        model = hello["model"]
        assert model is not None, hello
        c, r = model["center"], model["radius"]
        msg = {"type": "camera", "seq": 1, "width": 64, "height": 48, "channel": "final"}
        msg.update(eye=[c[0] + 3 * r, c[1], c[2] + r], target=c, up=[0, 0, 1], fov_y=40.0)
        ws.send(json.dumps({**msg, "still": True}))
        while True:
            data = ws.recv(timeout=60)
            if isinstance(data, bytes):
                header, jpeg = unpack_frame(data)
                assert jpeg[:2] == b"\xff\xd8"
                return {"model": model, "frame": header}


def test_the_whole_trip_through_the_bucket(
    s3: S3Server,
    bucket: str,
    server: LiveServer,
    workers: Workers,
    client: httpx.Client,
    scene: list[tuple[str, bytes]],
    roots: dict[str, Path],
) -> None:
    import trimesh

    scene_id = ready_scene(client, scene)  # upload (multipart, into the bucket) + commit
    keys = s3.keys(bucket, f"glint/scenes/{scene_id}/")
    assert len(keys) == len(scene)
    job_id = submit(client, scene_id, iterations=20)
    done = wait_state(client, job_id)
    assert done["state"] == "succeeded", (done["error"], workers.logs()[-3000:])
    assert f"job {job_id}: succeeded" in workers.logs()  # a Celery worker ran it

    arts = {a["name"]: a for a in list_all(client, f"/v1/jobs/{job_id}/artifacts")}
    assert {"checkpoint.pt", "point_cloud.ply", "mesh.glb", "report.md"} <= set(arts)
    in_bucket = s3.keys(bucket, f"glint/jobs/{job_id}/run/")
    assert sorted(f"glint/jobs/{job_id}/run/{n}" for n in arts) == in_bucket
    for name in ("point_cloud.ply", "mesh.glb"):
        r = client.get(arts[name]["url"])
        assert (
            r.status_code == 200 and hashlib.sha256(r.content).hexdigest() == arts[name]["sha256"]
        )
    mesh = trimesh.load(io.BytesIO(client.get(arts["mesh.glb"]["url"]).content), file_type="glb")
    assert len(mesh.geometry) >= 1
    ck = s3.client().get_object(Bucket=bucket, Key=f"glint/jobs/{job_id}/run/checkpoint.pt")
    whole = ck["Body"].read()
    r = client.get(arts["checkpoint.pt"]["url"], headers={"Range": "bytes=100-1123"})
    assert r.status_code == 206 and r.headers["content-range"] == f"bytes 100-1123/{len(whole)}"
    assert r.content == whole[100:1124]
    r = client.get(arts["checkpoint.pt"]["url"], headers={"Range": f"bytes={len(whole)}-"})
    assert r.status_code == 416

    # the viewer opens the checkpoint from the bucket
    seen = _viewer_frame(server, client, job_id)
    assert seen["model"]["iteration"] == 20 and seen["frame"]["width"] == 64

    # another mesh, on a worker, from the parent's checkpoint in the bucket
    r = client.post(f"/v1/jobs/{job_id}/meshes", json={"resolution": 32})
    assert r.status_code == 201, r.text
    mesh_job = wait_state(client, r.json()["id"])
    assert mesh_job["state"] == "succeeded", mesh_job["error"]
    names = {a["name"] for a in list_all(client, f"/v1/jobs/{mesh_job['id']}/artifacts")}
    assert {"mesh.ply", "mesh.glb", "mesh.json"} <= names

    # nothing of the run was ever on the API's disk but the viewer's copy of the checkpoint
    api_files = [f for f in _files(roots["api"]) if job_id in f or mesh_job["id"] in f]
    copies = [f for f in api_files if not f.startswith("cache/api/.state/")]  # ETags
    assert copies == [f"cache/api/jobs/{job_id}/run/checkpoint.pt"], api_files
    for name in ("worker-a", "worker-b"):  # run folders are dropped once they are stored
        wait_for(lambda name=name: _dropped(roots[name], job_id), timeout=30)

    assert client.delete(f"/v1/jobs/{job_id}").status_code == 204  # with its mesh job
    assert s3.keys(bucket, f"glint/jobs/{job_id}/") == []
    assert s3.keys(bucket, f"glint/jobs/{mesh_job['id']}/") == []
    assert not [f for f in _files(roots["api"]) if job_id in f]  # and the API's copy


def test_photos_without_poses_through_the_bucket(
    s3: S3Server, bucket: str, workers: Workers, client: httpx.Client, roots: dict[str, Path]
) -> None:
    """Issue 23: a Celery worker recovers the cameras of an images-only scene from the
    bucket, stores the SfM scene beside the run, trains on it; a mesh job reads it back."""
    files = photo_files()
    scene_id = ready_scene(client, files)
    job_id = submit(client, scene_id, iterations=10, outputs={"mesh": False})
    done = wait_state(client, job_id)
    assert done["state"] == "succeeded", (done["error"], workers.logs()[-3000:])
    assert done["sfm"]["result"]["registered"] == VIEWS

    arts = {a["name"] for a in list_all(client, f"/v1/jobs/{job_id}/artifacts")}
    sfm = {"sfm_report.json", "sfm_report.txt", "sparse/0/cameras.bin", "sparse/0/images.bin"}
    assert sfm | {"checkpoint.pt"} <= arts, arts
    assert sorted(f"glint/jobs/{job_id}/run/{n}" for n in arts) == s3.keys(
        bucket, f"glint/jobs/{job_id}/run/"
    )
    scene_keys = s3.keys(bucket, f"glint/jobs/{job_id}/scene/")
    assert f"glint/jobs/{job_id}/scene/sparse/0/points3D.bin" in scene_keys
    assert len([k for k in scene_keys if "/scene/images/" in k]) == VIEWS
    assert len(s3.keys(bucket, f"glint/scenes/{scene_id}/")) == len(files)  # as uploaded

    r = client.post(f"/v1/jobs/{job_id}/meshes", json={"resolution": 24})
    assert r.status_code == 201, r.text
    mesh_job = wait_state(client, r.json()["id"])
    assert mesh_job["state"] == "succeeded", mesh_job["error"]
    for name in ("worker-a", "worker-b"):  # local copies are dropped once stored
        wait_for(lambda name=name: _dropped(roots[name], job_id), timeout=30)
    assert client.delete(f"/v1/jobs/{job_id}").status_code == 204
    assert s3.keys(bucket, f"glint/jobs/{job_id}/") == []


def _iteration(c: httpx.Client, job_id: str) -> int:
    j = job(c, job_id)
    assert j["state"] in ("queued", "running"), j
    return int(j["iteration"])


def test_outage_mid_job_then_another_host_resumes_from_the_bucket(
    s3: S3Server,
    bucket: str,
    server: LiveServer,
    workers: Workers,
    client: httpx.Client,
    scene: list[tuple[str, bytes]],
) -> None:
    """The endpoint stops answering while a job trains: the API says so at once, the
    worker retries with backoff and carries on when it is back. Then that worker's host
    dies: the other worker, which has never seen the job, resumes it from the bucket."""
    scene_id = ready_scene(client, scene)
    job_id = submit(client, scene_id, iterations=400, checkpoint_every=10)
    wait_for(lambda: _iteration(client, job_id) >= 20, timeout=120, every=0.1)
    # its checkpoints are in the bucket, yet nothing is listed before the run is stored
    assert f"glint/jobs/{job_id}/run/checkpoint.pt" in s3.keys(bucket, f"glint/jobs/{job_id}/")
    assert list_all(client, f"/v1/jobs/{job_id}/artifacts") == []
    busy = [w["id"] for w in list_all(client, "/v1/workers") if w["current_job"] == job_id]
    (runner,) = [w for w in workers.procs.values() if w.node in busy]

    s3.pause()
    try:
        t0 = time.monotonic()
        r = client.get("/v1/health")
        assert r.status_code == 503 and r.json()["type"] == "urn:glint:problem:store-unavailable"
        r = client.post("/v1/jobs", json={"scene_id": scene_id, "config": {"iterations": 5}})
        assert r.status_code == 503 and r.json()["type"] == "urn:glint:problem:store-unavailable"
        assert time.monotonic() - t0 < 10  # two answers, neither a hang
        wait_for(lambda: "store unavailable (attempt" in runner.log(), timeout=30)
        stalled = _iteration(client, job_id)
    finally:
        s3.resume()
    wait_for(lambda: "store reachable again" in runner.log(), timeout=60)
    wait_for(lambda: _iteration(client, job_id) >= stalled + 20, timeout=120, every=0.1)
    assert job(client, job_id)["attempts"] == 1  # the same run carried on
    assert client.get("/v1/health").status_code == 200

    runner.kill()  # its host is gone, and its local copy of the run with it
    other = next(w for w in workers.procs.values() if w is not runner)
    done = wait_state(client, job_id, timeout=180)
    assert done["state"] == "succeeded", (done["error"], other.log()[-3000:])
    assert done["attempts"] == 2, done
    resumed = [
        int(m) for m in re.findall(rf"job {job_id}: resumed from iteration (\d+)", other.log())
    ]
    assert resumed and resumed[0] >= 10, other.log()[-3000:]
