"""Scenes over HTTP: archives that are fine, re-uploads, file deletion, listing, deletion."""

from __future__ import annotations

import hashlib

import httpx

from tests.api.archives import make_tar, make_zip
from tests.api.support import LiveServer, list_all, multipart, store_files


def _new(client: httpx.Client, name: str = "s") -> str:
    r = client.post("/v1/scenes", json={"name": name})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def test_zip_archive_with_top_folder_validates(client, scene) -> None:
    sid = _new(client)
    data = make_zip([(f"sphere/{name}", body) for name, body in scene])
    r = client.post(
        f"/v1/scenes/{sid}/archive", content=data, headers={"Content-Type": "application/zip"}
    )
    assert r.status_code == 201, r.text
    assert r.json()["scene"]["file_count"] == len(scene)
    r = client.post(f"/v1/scenes/{sid}/commit")
    assert r.status_code == 200, r.text
    assert r.json()["report"]["views"] == 8


def test_tar_gz_archive_plus_multipart_part(client, scene) -> None:
    """Archives and multipart uploads combine; './' prefixes (tar -C dir .) are dropped."""
    sid = _new(client)
    images = [(n, b) for n, b in scene if n.endswith(".png")]
    meta = [(n, b) for n, b in scene if not n.endswith(".png")]
    r = client.post(
        f"/v1/scenes/{sid}/archive",
        content=make_tar([(f"./{n}", b) for n, b in images]),
        headers={"Content-Type": "application/gzip"},
    )
    assert r.status_code == 201, r.text
    assert {f["path"] for f in r.json()["files"]} == {n for n, _ in images}
    assert client.post(f"/v1/scenes/{sid}/files", files=multipart(meta)).status_code == 201
    assert client.post(f"/v1/scenes/{sid}/commit").json()["state"] == "ready"


def test_reupload_replaces_and_delete_removes(server: LiveServer, client) -> None:
    sid = _new(client)
    client.post(f"/v1/scenes/{sid}/files", files=multipart([("a.txt", b"one"), ("b.txt", b"2")]))
    r = client.post(f"/v1/scenes/{sid}/files", files=multipart([("a.txt", b"three")]))
    assert r.status_code == 201
    assert r.json()["scene"]["file_count"] == 2
    assert r.json()["scene"]["total_bytes"] == len(b"three") + 1
    files = {f["path"]: f for f in list_all(client, f"/v1/scenes/{sid}/files")}
    assert files["a.txt"]["sha256"] == hashlib.sha256(b"three").hexdigest()
    stored = server.settings.store_root / "scenes" / sid / "files" / "a.txt"
    assert stored.read_bytes() == b"three"

    assert client.delete(f"/v1/scenes/{sid}/files/b.txt").status_code == 204
    assert client.delete(f"/v1/scenes/{sid}/files/b.txt").status_code == 404
    assert [f["path"] for f in list_all(client, f"/v1/scenes/{sid}/files")] == ["a.txt"]

    assert client.delete(f"/v1/scenes/{sid}").status_code == 204
    assert client.get(f"/v1/scenes/{sid}").status_code == 404
    assert not [f for f in store_files(server.settings.store_root) if sid in f]


def test_nested_paths_and_unicode_names(client) -> None:
    sid = _new(client)
    r = client.post(
        f"/v1/scenes/{sid}/files",
        files=multipart([("images/déjà vu.png", b"x"), ("./sparse/0/cameras.txt", b"# c")]),
    )
    assert r.status_code == 201, r.text
    paths = sorted(f["path"] for f in r.json()["files"])
    assert paths == ["images/déjà vu.png", "sparse/0/cameras.txt"]


def test_list_scenes_with_state_filter(client, scene) -> None:
    open_id = _new(client, "first")
    ready_id = _new(client, "second")
    client.post(f"/v1/scenes/{ready_id}/files", files=multipart(scene))
    client.post(f"/v1/scenes/{ready_id}/commit")
    everything = client.get("/v1/scenes").json()
    assert everything["total"] == 2
    assert [s["id"] for s in everything["items"]] == [ready_id, open_id]  # newest first
    ready = client.get("/v1/scenes", params={"state": "ready"}).json()
    assert [s["id"] for s in ready["items"]] == [ready_id]
    assert ready["items"][0]["file_count"] == len(scene)
    page = client.get("/v1/scenes", params={"limit": 1, "offset": 1}).json()
    assert [s["id"] for s in page["items"]] == [open_id] and page["total"] == 2
    # a committed scene's files are frozen
    assert client.delete(f"/v1/scenes/{ready_id}/files/transforms_train.json").status_code == 409
