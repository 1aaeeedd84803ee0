"""The client against the distributed setup: the API with its store in an S3 bucket (moto's
real S3 endpoint, credentials checked), jobs on a Celery worker process through Redis.
Chunked uploads land in the bucket, a killed upload resumes there, and the artifacts a
worker sent to the bucket come back whole."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from glint_client import Client

from tests.api.support import LiveServer, make_settings
from tests.client.conftest import QUICK_CONFIG
from tests.client.support import CountingTransport, Killed, sha256
from tests.s3_server import S3Server
from tests.worker.support import RedisServer, Workers, needs_redis

pytestmark = needs_redis


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[LiveServer, S3Server, str]]:
    s3 = S3Server(tmp_path_factory.mktemp("moto")).start()
    redis = RedisServer(tmp_path_factory.mktemp("redis")).start()
    bucket = s3.bucket()
    api_root, worker_root = tmp_path_factory.mktemp("api"), tmp_path_factory.mktemp("worker")
    db = f"sqlite:///{tmp_path_factory.mktemp('db') / 'glint.db'}"
    settings = make_settings(
        api_root, db, redis_url=redis.url, store_sweep_s=0, **s3.settings(bucket)
    )
    server = LiveServer(settings, None).start()
    workers = Workers(server, redis.url, tmp_path_factory.mktemp("logs"), **s3.env(bucket))
    try:
        w = workers.start("a", GLINT_DATA_DIR=str(worker_root), GLINT_STORE_DIR=str(worker_root))
        w.wait_ready()
        yield server, s3, bucket
    finally:
        workers.stop_all()
        server.stop()
        redis.stop()
        s3.stop()


def test_client_through_celery_and_s3(
    stack: tuple[LiveServer, S3Server, str], scene_dir: Path, tmp_path: Path
) -> None:
    server, s3, bucket = stack
    key = server.new_key("client-s3")
    files = sorted(p for p in scene_dir.rglob("*") if p.is_file())

    chunks = 0

    def die_after_three_chunks(request, n: int) -> None:  # type: ignore[no-untyped-def]
        nonlocal chunks
        if request.method == "PATCH":
            chunks += 1
            if chunks > 3:
                raise Killed

    with Client(server.url, key, transport=CountingTransport(die_after_three_chunks)) as c:
        scene_id = c.create_scene("sphere-s3")["id"]
        with pytest.raises(Killed):
            c.upload(scene_id, scene_dir, chunk_bytes=4096, parallel=1)

    counter = CountingTransport()
    with Client(server.url, key, transport=counter) as c:
        held = sum(f["size"] for f in c.scene_files(scene_id))
        held += sum(u["offset"] for u in c.uploads(scene_id))
        assert held > 0
        scene = c.create_scene_from(scene_dir, scene_id=scene_id)  # resume, then commit
        assert scene["state"] == "ready"
        assert counter.sent("PATCH") == sum(p.stat().st_size for p in files) - held
        assert len(s3.keys(bucket, f"glint/scenes/{scene_id}/files/")) == len(files)

        job = c.wait(c.create_job(scene_id, QUICK_CONFIG)["id"])
        assert job["state"] == "succeeded", job["error"]
        arts = {a["name"]: a for a in c.artifacts(job["id"])}
        assert sorted(f"glint/jobs/{job['id']}/run/{n}" for n in arts) == s3.keys(
            bucket, f"glint/jobs/{job['id']}/run/"
        )
        paths = c.download(job["id"], tmp_path, ["checkpoint.pt", "point_cloud.ply", "*.md"])
        assert {p.name for p in paths} >= {"checkpoint.pt", "point_cloud.ply", "report.md"}
        for p in paths:
            assert sha256(p) == arts[p.relative_to(tmp_path).as_posix()]["sha256"]
