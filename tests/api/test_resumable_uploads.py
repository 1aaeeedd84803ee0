"""Resumable uploads over HTTP: chunks from an offset, a cut-off chunk, resume, checksums."""

from __future__ import annotations

import hashlib
import os
import socket
import time
from typing import Any

import httpx
import pytest

from api.service.chunk_uploads import uploads_key
from api.service.sweeper import sweep
from tests.api.support import LiveServer, list_all, store_files

CHUNK = {"Content-Type": "application/offset+octet-stream"}


def _scene(client: httpx.Client) -> str:
    r = client.post("/v1/scenes", json={"name": "chunks"})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _announce(client: httpx.Client, sid: str, path: str, data: bytes) -> httpx.Response:
    body = {"path": path, "size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    return client.post(f"/v1/scenes/{sid}/uploads", json=body)


def _send(client: httpx.Client, sid: str, uid: str, offset: int, data: bytes) -> httpx.Response:
    headers = {**CHUNK, "Upload-Offset": str(offset)}
    return client.patch(f"/v1/scenes/{sid}/uploads/{uid}", content=data, headers=headers)


def _upload(client: httpx.Client, sid: str, path: str, data: bytes, chunk: int) -> dict[str, Any]:
    r = _announce(client, sid, path, data)
    assert r.status_code in (200, 201), r.text
    up = r.json()
    while up["state"] == "open":
        r = _send(client, sid, up["id"], up["offset"], data[up["offset"] : up["offset"] + chunk])
        assert r.status_code == 200, r.text
        up = r.json()
    return up


def test_a_scene_uploaded_in_chunks_commits(client, scene) -> None:
    sid = _scene(client)
    for name, body in scene:
        up = _upload(client, sid, name, body, chunk=700)
        assert up["state"] == "complete" and up["id"] is None
        assert up["file"] == {
            "path": name,
            "size": len(body),
            "sha256": hashlib.sha256(body).hexdigest(),
        }
    r = client.post(f"/v1/scenes/{sid}/commit")
    assert r.status_code == 200, r.text
    assert r.json()["file_count"] == len(scene)


def test_resume_sends_only_the_rest_and_finds_the_upload_again(client) -> None:
    """A client that lost everything announces the file again and gets the server's offset."""
    data = os.urandom(10_000)
    sid = _scene(client)
    r = _announce(client, sid, "images/a.bin", data)
    assert r.status_code == 201, r.text
    up = r.json()
    assert up["offset"] == 0 and up["state"] == "open" and up["chunk_max_bytes"] > 0
    assert _send(client, sid, up["id"], 0, data[:4000]).json()["offset"] == 4000
    # a new client process: same announcement, same upload, its offset
    again = _announce(client, sid, "images/a.bin", data)
    assert again.status_code == 200
    assert again.json()["id"] == up["id"] and again.json()["offset"] == 4000
    got = client.get(f"/v1/scenes/{sid}/uploads/{up['id']}")
    assert got.json()["offset"] == 4000 and got.headers["Upload-Offset"] == "4000"
    # a stale offset is refused, naming where to go on
    r = _send(client, sid, up["id"], 0, data[:4000])
    assert r.status_code == 409
    problem = r.json()
    assert problem["type"] == "urn:glint:problem:offset-mismatch"
    assert problem["offset"] == 4000 and r.headers["Upload-Offset"] == "4000"
    r = _send(client, sid, up["id"], 4000, data[4000:])
    assert r.status_code == 200 and r.json()["state"] == "complete"
    files = {f["path"]: f for f in list_all(client, f"/v1/scenes/{sid}/files")}
    assert files["images/a.bin"]["sha256"] == hashlib.sha256(data).hexdigest()
    # announced once more: already there, nothing to send
    done = _announce(client, sid, "images/a.bin", data)
    assert done.status_code == 200 and done.json()["state"] == "complete"
    assert list_all(client, f"/v1/scenes/{sid}/uploads") == []


def test_a_chunk_cut_off_midway_is_dropped_whole(server: LiveServer, key: str, client) -> None:
    data = os.urandom(50_000)
    sid = _scene(client)
    up = _announce(client, sid, "big.bin", data).json()
    assert _send(client, sid, up["id"], 0, data[:10_000]).status_code == 200
    # a raw request that promises 20 000 bytes and dies after 5 000
    host, port = server.url.removeprefix("http://").split(":")
    head = (
        f"PATCH /v1/scenes/{sid}/uploads/{up['id']} HTTP/1.1\r\nHost: {host}\r\n"
        f"Authorization: Bearer {key}\r\nContent-Type: application/offset+octet-stream\r\n"
        f"Upload-Offset: 10000\r\nContent-Length: 20000\r\n\r\n"
    ).encode()
    with socket.create_connection((host, int(port))) as sock:
        sock.sendall(head + data[10_000:15_000])
    time.sleep(1.0)  # the server notices the dead connection on its own time
    assert client.get(f"/v1/scenes/{sid}/uploads/{up['id']}").json()["offset"] == 10_000
    assert len(server.app.state.store.list(uploads_key(sid, up["id"]))) == 1  # chunk 1 only
    r = _send(client, sid, up["id"], 10_000, data[10_000:])
    assert r.status_code == 200 and r.json()["state"] == "complete", r.text


def test_checksum_mismatch_resets_the_upload(client) -> None:
    data = os.urandom(3000)
    sid = _scene(client)
    body = {"path": "x.bin", "size": 3000, "sha256": hashlib.sha256(b"other").hexdigest()}
    up = client.post(f"/v1/scenes/{sid}/uploads", json=body).json()
    assert _send(client, sid, up["id"], 0, data[:2000]).status_code == 200
    r = _send(client, sid, up["id"], 2000, data[2000:])
    assert r.status_code == 422
    assert r.json()["type"] == "urn:glint:problem:checksum-mismatch"
    assert r.json()["offset"] == 0
    assert client.get(f"/v1/scenes/{sid}/uploads/{up['id']}").json()["offset"] == 0
    assert list_all(client, f"/v1/scenes/{sid}/files") == []


@pytest.mark.parametrize(
    ("body", "status", "field"),
    [
        ({"path": "../up.bin", "size": 3, "sha256": "0" * 64}, 422, "body.path"),
        ({"path": "a.bin", "size": -1, "sha256": "0" * 64}, 422, "body.size"),
        ({"path": "a.bin", "size": 3, "sha256": "xyz"}, 422, "body.sha256"),
        ({"path": "a.bin", "size": 3 * 2**40, "sha256": "0" * 64}, 413, "body.size"),
    ],
)
def test_bad_announcements_name_the_field(client, body, status, field) -> None:
    sid = _scene(client)
    r = client.post(f"/v1/scenes/{sid}/uploads", json=body)
    assert r.status_code == status, r.text
    assert field in [e["field"] for e in r.json()["errors"]]
    assert list_all(client, f"/v1/scenes/{sid}/uploads") == []


def test_bad_chunks_are_refused_and_change_nothing(client) -> None:
    data = os.urandom(2000)
    sid = _scene(client)
    up = _announce(client, sid, "a.bin", data).json()
    url = f"/v1/scenes/{sid}/uploads/{up['id']}"
    assert client.patch(url, content=data, headers=CHUNK).status_code == 400  # no offset
    r = client.patch(url, content=data, headers={"Upload-Offset": "0"})
    assert r.status_code == 415
    r = _send(client, sid, up["id"], 0, data + b"more")  # past the file's end
    assert r.status_code == 413
    assert client.get(url).json()["offset"] == 0


def test_commit_and_delete_drop_unfinished_uploads(server: LiveServer, client, scene) -> None:
    sid = _scene(client)
    for name, body in scene:
        _upload(client, sid, name, body, chunk=10_000)
    extra = os.urandom(5000)
    up = _announce(client, sid, "notes/extra.bin", extra).json()
    _send(client, sid, up["id"], 0, extra[:100])
    gone = _announce(client, sid, "notes/gone.bin", extra).json()
    _send(client, sid, gone["id"], 0, extra[:100])
    assert client.delete(f"/v1/scenes/{sid}/uploads/{gone['id']}").status_code == 204
    assert client.get(f"/v1/scenes/{sid}/uploads/{gone['id']}").status_code == 404
    assert client.post(f"/v1/scenes/{sid}/commit").status_code == 200
    assert list_all(client, f"/v1/scenes/{sid}/uploads") == []
    store = server.app.state.store
    assert store.list(uploads_key(sid)) == []
    r = _send(client, sid, up["id"], 100, extra[100:])
    assert r.status_code in (404, 409)


def test_the_sweep_removes_uploads_nobody_finished(server: LiveServer, client) -> None:
    sid = _scene(client)
    data = os.urandom(1000)
    up = _announce(client, sid, "old.bin", data).json()
    _send(client, sid, up["id"], 0, data[:10])
    store = server.app.state.store
    assert any(uploads_key(sid) in f for f in store_files(server.settings.store_root))
    sweep(server.database, store, upload_idle_s=3600)  # not idle long enough: kept
    assert client.get(f"/v1/scenes/{sid}/uploads/{up['id']}").status_code == 200
    sweep(server.database, store, upload_idle_s=0)
    assert client.get(f"/v1/scenes/{sid}/uploads/{up['id']}").status_code == 404
    assert store.list(uploads_key(sid)) == []


def test_an_empty_file_completes_when_announced(client) -> None:
    sid = _scene(client)
    r = _announce(client, sid, "empty.txt", b"")
    assert r.status_code == 200 and r.json()["state"] == "complete", r.text
    assert [f["path"] for f in list_all(client, f"/v1/scenes/{sid}/files")] == ["empty.txt"]
