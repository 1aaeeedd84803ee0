"""Uploads that survive: a client killed halfway is resumed by a new one that sends only
the rest (bytes counted on the wire and checked against what the server says it holds);
archives and loose photos become scenes too."""

from __future__ import annotations

import os
import tarfile
import threading
import zipfile
from pathlib import Path

import httpx
import pytest
from glint_client import Client, GlintClientError, ServerError

from tests.api.support import LiveServer
from tests.client.support import CountingTransport, Killed, sha256

CHUNK = 32 * 1024


def _held(c: Client, scene_id: str) -> int:
    """Bytes the server holds for the scene: whole files plus unfinished uploads' offsets."""
    files = sum(f["size"] for f in c.scene_files(scene_id))
    return files + sum(u["offset"] for u in c.uploads(scene_id))


def test_upload_killed_halfway_resumes_sending_only_the_rest(
    server: LiveServer, key: str, tmp_path: Path
) -> None:
    folder = tmp_path / "capture"
    (folder / "train").mkdir(parents=True)
    sizes = {"train/a.bin": 300_000, "train/b.bin": 200_000, "notes.txt": 1_000}
    for name, size in sizes.items():
        (folder / name).write_bytes(os.urandom(size))
    total = sum(sizes.values())

    lock = threading.Lock()
    patches = 0

    def die_after_six_chunks(request: httpx.Request, n: int) -> None:
        nonlocal patches
        if request.method == "PATCH":
            with lock:
                patches += 1
                if patches > 6:
                    raise Killed  # the process dies here, mid-upload

    first = CountingTransport(before=die_after_six_chunks)
    with Client(server.url, key, transport=first) as c:
        scene_id = c.create_scene("killed")["id"]
        with pytest.raises(Killed):
            c.upload(scene_id, folder, chunk_bytes=CHUNK, parallel=2)

    second = CountingTransport()
    with Client(server.url, key, transport=second) as c:  # a new process: no local state
        held = _held(c, scene_id)
        assert held == first.sent("PATCH")  # every chunk the dead client sent was kept
        assert 0 < held < total
        uploads = c.upload(scene_id, folder, chunk_bytes=CHUNK, parallel=2)
        assert second.sent("PATCH") == total - held  # measured: only the rest went
        assert {u["path"] for u in uploads} == set(sizes)
        assert all(u["state"] == "complete" for u in uploads)
        on_server = {f["path"]: f["sha256"] for f in c.scene_files(scene_id)}
        assert on_server == {name: sha256(folder / name) for name in sizes}
        assert list(c.uploads(scene_id)) == []

        # a third run finds every file there and sends no byte at all
        third = CountingTransport()
        with Client(server.url, key, transport=third) as again:
            again.upload(scene_id, folder, chunk_bytes=CHUNK)
        assert third.count("PATCH") == 0


def test_archives_and_photos_become_scenes(glint: Client, scene_dir: Path, tmp_path: Path) -> None:
    # a zip of the folder (one wrapping folder, as zipping a folder makes) and a .tgz of it
    zpath = tmp_path / "sphere.zip"
    with zipfile.ZipFile(zpath, "w") as z:
        for p in sorted(scene_dir.rglob("*")):
            if p.is_file():
                z.write(p, f"sphere/{p.relative_to(scene_dir).as_posix()}")
    tpath = tmp_path / "sphere.tgz"
    with tarfile.open(tpath, "w:gz") as t:
        t.add(scene_dir, ".")
    for archive in (zpath, tpath):
        scene = glint.create_scene_from(archive)
        assert scene["state"] == "ready" and scene["format"] == "blender", archive
        assert scene["name"] == "sphere"
    # or as one request, unpacked by the server
    scene_id = glint.create_scene("whole-archive")["id"]
    assert len(glint.upload_archive(scene_id, tpath)["files"]) == scene["file_count"]
    assert glint.commit(scene_id)["state"] == "ready"

    # photos without poses, given as files: top level, and commit says SfM is needed
    from tests.photo_capture import photo_files

    photos = []
    for name, data in photo_files(3, folder="", masks=False):
        (tmp_path / "photos").mkdir(exist_ok=True)
        photos.append(tmp_path / "photos" / name)
        photos[-1].write_bytes(data)
    scene = glint.create_scene_from(photos)
    assert scene["name"] == "photos"
    assert scene["report"] is not None and scene["report"].get("needs_sfm") is True

    # an archive member that would leave the folder is refused before any file is sent
    evil = tmp_path / "evil.zip"
    with zipfile.ZipFile(evil, "w") as z:
        z.writestr("../outside.txt", b"x")
    with pytest.raises(GlintClientError, match="outside"):
        glint.create_scene_from(evil)


class FailingChunks(httpx.HTTPTransport):
    """Answers ``fail`` chunk PATCHes with a 500 problem without passing them on."""

    def __init__(self, fail: set[int]) -> None:
        super().__init__()
        self.fail = fail
        self.patches = 0

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if request.method == "PATCH":
            self.patches += 1
            if self.patches in self.fail:
                problem = {"type": "urn:glint:problem:internal-error", "status": 500}
                return httpx.Response(500, json=problem, request=request)
        return super().handle_request(request)


def test_a_chunk_refused_by_a_server_fault_is_sent_again(
    server: LiveServer, key: str, tmp_path: Path
) -> None:
    data = os.urandom(5 * CHUNK + 100)
    (tmp_path / "f.bin").write_bytes(data)
    transport = FailingChunks({2, 4, 5})
    with Client(server.url, key, transport=transport) as c:
        scene_id = c.create_scene("faults")["id"]
        (up,) = c.upload(scene_id, tmp_path / "f.bin", chunk_bytes=CHUNK)
        assert up["state"] == "complete" and transport.patches == 6 + 3
        assert [f["sha256"] for f in c.scene_files(scene_id)] == [sha256(tmp_path / "f.bin")]

    transport = FailingChunks({1, 2, 3, 4})  # more faults in a row than the client takes
    with Client(server.url, key, transport=transport) as c, pytest.raises(ServerError):
        c.upload(c.create_scene("down")["id"], tmp_path / "f.bin", chunk_bytes=CHUNK)
