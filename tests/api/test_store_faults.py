"""The API on an S3 store (a real S3 endpoint: moto's server) when things go wrong: wrong
credentials, an endpoint that does not answer, an upload cut off mid-way, objects that no
row accounts for. Each answer is quick and problem+json; nothing half-written is kept."""

from __future__ import annotations

import hashlib
import socket
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from sqlalchemy import delete

from api.service.models import Scene, SceneFile
from api.service.sweeper import Sweeper, sweep
from tests.api.support import LiveServer, ThreadQueue, make_settings, multipart, wait_for
from tests.s3_server import PART_BYTES, S3Server

QUICK_S = 5.0  # "not a hang": the store check waits at most min(3, store_timeout_s)


@pytest.fixture(scope="module")
def s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Server]:
    srv = S3Server(tmp_path_factory.mktemp("moto")).start()
    yield srv
    srv.stop()


def _server(root: Path, **store: object) -> LiveServer:
    settings = make_settings(
        root, max_file_bytes=64 << 20, max_scene_bytes=128 << 20, store_sweep_s=0, **store
    )
    return LiveServer(settings, ThreadQueue(settings)).start()


@pytest.fixture(scope="module")
def bucket(s3: S3Server) -> str:
    return s3.bucket()


@pytest.fixture(scope="module")
def good(
    s3: S3Server, bucket: str, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[LiveServer]:
    srv = _server(tmp_path_factory.mktemp("api"), **s3.settings(bucket))
    yield srv
    srv.stop()


def _client(srv: LiveServer) -> httpx.Client:
    return srv.client(srv.new_key(f"owner-{uuid.uuid4().hex[:8]}"))


def _problem(r: httpx.Response, status: int, slug: str) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert body["type"] == f"urn:glint:problem:{slug}", body
    return body


@pytest.mark.parametrize("fault", ["wrong-credentials", "unreachable"])
def test_a_store_that_cannot_be_used_answers_503_quickly(
    s3: S3Server, bucket: str, tmp_path: Path, fault: str
) -> None:
    if fault == "wrong-credentials":
        store = s3.settings(bucket, s3_secret_access_key="wrong-secret")
        said = "refused the credentials"
    else:  # nothing listens on the port
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        store = s3.settings(bucket, s3_endpoint_url=f"http://127.0.0.1:{port}")
        said = "unreachable"
    srv = _server(tmp_path, **store)  # starts: a dead store does not stop the API
    try:
        with _client(srv) as c:
            t0 = time.monotonic()
            body = _problem(c.get("/v1/health"), 503, "store-unavailable")
            assert said in body["detail"] and time.monotonic() - t0 < QUICK_S
            sid = c.post("/v1/scenes", json={"name": "s"}).json()["id"]  # the database works
            t0 = time.monotonic()
            r = c.post("/v1/jobs", json={"scene_id": sid, "config": {"iterations": 5}})
            _problem(r, 503, "store-unavailable")
            assert time.monotonic() - t0 < QUICK_S
            r = c.post(f"/v1/scenes/{sid}/files", files=multipart([("a.txt", b"a")]))
            _problem(r, 503, "store-unavailable")
            assert c.get(f"/v1/scenes/{sid}/files").json()["total"] == 0
            assert c.get("/v1/jobs").json()["total"] == 0  # nothing was created
    finally:
        srv.stop()


def test_health_reports_the_store(good: LiveServer) -> None:
    with good.client(None) as c:
        r = c.get("/v1/health")
    assert r.status_code == 200 and r.json()["store"] == "ok", r.text


def test_interrupted_upload_leaves_no_parts_and_can_be_sent_again(
    s3: S3Server, bucket: str, good: LiveServer
) -> None:
    """A client that goes away mid-file: its multipart upload is aborted (parts already
    in the bucket dropped), nothing is listed; the scene takes the upload again."""
    key = good.new_key(f"owner-{uuid.uuid4().hex[:8]}")
    with good.client(key) as c:
        sid = c.post("/v1/scenes", json={"name": "big"}).json()["id"]
    size = 3 * PART_BYTES
    boundary = "glintboundary"
    head = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="files"; filename="big.bin"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n"
    ).encode()
    tail = f"\r\n--{boundary}--\r\n".encode()
    request = (
        f"POST /v1/scenes/{sid}/files HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        f"Authorization: Bearer {key}\r\n"
        f"Content-Type: multipart/form-data; boundary={boundary}\r\n"
        f"Content-Length: {len(head) + size + len(tail)}\r\n\r\n"
    ).encode()
    with socket.create_connection(("127.0.0.1", good.port)) as sock:
        sock.sendall(request + head)
        chunk = b"\x01" * (1 << 20)
        for _ in range(2 * PART_BYTES // len(chunk) + 1):  # two parts and a bit
            sock.sendall(chunk)
        wait_for(lambda: s3.uploads(bucket), timeout=30)  # parts are in the bucket
    # the connection is gone: the API aborts the upload
    wait_for(lambda: not s3.uploads(bucket), timeout=30)
    assert not [k for k in s3.keys(bucket) if sid in k]
    with good.client(key) as c:
        assert c.get(f"/v1/scenes/{sid}/files").json()["total"] == 0
        data = b"\x02" * (PART_BYTES + 7)
        r = c.post(f"/v1/scenes/{sid}/files", files=multipart([("big.bin", data)]))
        assert r.status_code == 201, r.text
        assert r.json()["files"][0]["size"] == len(data)
    assert [k for k in s3.keys(bucket) if sid in k] == [f"glint/scenes/{sid}/files/big.bin"]
    assert not s3.uploads(bucket)


def test_deletes_remove_objects_and_the_sweep_removes_orphans(
    s3: S3Server, bucket: str, good: LiveServer
) -> None:
    with _client(good) as c:
        kept = c.post("/v1/scenes", json={"name": "kept"}).json()["id"]
        gone = c.post("/v1/scenes", json={"name": "deleted"}).json()["id"]
        orphan = c.post("/v1/scenes", json={"name": "orphan"}).json()["id"]
        for sid in (kept, gone, orphan):
            r = c.post(f"/v1/scenes/{sid}/files", files=multipart([("a.txt", b"a")]))
            assert r.status_code == 201, r.text
        assert c.delete(f"/v1/scenes/{gone}").status_code == 204
    assert not [k for k in s3.keys(bucket) if gone in k]  # deleted with its row
    # a row removed while its objects stayed (a crash, a store down at delete time)
    with good.database.write() as s:
        s.execute(delete(SceneFile).where(SceneFile.scene_id == orphan))
        s.execute(delete(Scene).where(Scene.id == orphan))
    abandoned = s3.client().create_multipart_upload(Bucket=bucket, Key="glint/scenes/x/files/y")
    # the API's periodic sweep (GLINT_STORE_SWEEP_S; here every 0.2 s, no grace)
    sweeper = Sweeper(good.database, good.app.state.store, period_s=0.2, grace_s=0).start()
    try:
        wait_for(lambda: not [k for k in s3.keys(bucket) if orphan in k], timeout=30)
        wait_for(lambda: not s3.uploads(bucket), timeout=30)
    finally:
        sweeper.close()
    assert sweep(good.database, good.app.state.store, grace_s=0).scenes == 0  # nothing left
    keys = s3.keys(bucket)
    assert not [k for k in keys if orphan in k]
    assert f"glint/scenes/{kept}/files/a.txt" in keys  # what a row accounts for stays
    assert abandoned["UploadId"] not in {u["UploadId"] for u in s3.uploads(bucket)}


def test_resumable_upload_through_the_bucket_sends_only_the_rest(
    s3: S3Server, bucket: str, good: LiveServer
) -> None:
    """Chunks are objects in the bucket: one cut off midway leaves nothing, the upload
    goes on from the server's offset, and completion leaves exactly the scene file."""
    key = good.new_key(f"owner-{uuid.uuid4().hex[:8]}")
    data = bytes(range(256)) * (PART_BYTES // 128 + 3)  # over two store parts
    sha = hashlib.sha256(data).hexdigest()
    with good.client(key) as c:
        sid = c.post("/v1/scenes", json={"name": "chunks"}).json()["id"]
        announce = {"path": "big.bin", "size": len(data), "sha256": sha}
        up = c.post(f"/v1/scenes/{sid}/uploads", json=announce).json()
        half = len(data) // 2
        r = c.patch(
            f"/v1/scenes/{sid}/uploads/{up['id']}",
            content=data[:half],
            headers={"Upload-Offset": "0", "Content-Type": "application/offset+octet-stream"},
        )
        assert r.status_code == 200 and r.json()["offset"] == half, r.text
    request = (
        f"PATCH /v1/scenes/{sid}/uploads/{up['id']} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        f"Authorization: Bearer {key}\r\nContent-Type: application/offset+octet-stream\r\n"
        f"Upload-Offset: {half}\r\nContent-Length: {len(data) - half}\r\n\r\n"
    ).encode()
    with socket.create_connection(("127.0.0.1", good.port)) as sock:
        sock.sendall(request + data[half : half + PART_BYTES // 2])  # then the line drops
    chunks = f"glint/scenes/{sid}/uploads/{up['id']}/"
    wait_for(lambda: not s3.uploads(bucket), timeout=30)  # the cut chunk's write aborted
    assert len([k for k in s3.keys(bucket) if k.startswith(chunks)]) == 1
    with good.client(key) as c:
        again = c.post(f"/v1/scenes/{sid}/uploads", json=announce).json()
        assert again["id"] == up["id"] and again["offset"] == half
        r = c.patch(
            f"/v1/scenes/{sid}/uploads/{up['id']}",
            content=data[half:],
            headers={"Upload-Offset": str(half), "Content-Type": "application/offset+octet-stream"},
        )
        assert r.status_code == 200 and r.json()["state"] == "complete", r.text
        assert r.json()["file"]["sha256"] == sha
    assert [k for k in s3.keys(bucket) if sid in k] == [f"glint/scenes/{sid}/files/big.bin"]
    assert not s3.uploads(bucket)
