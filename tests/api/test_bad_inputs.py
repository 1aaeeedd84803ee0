"""Hostile and mistaken requests: each gets the right 4xx as problem+json naming the problem.

Every case also checks that the store holds no partial files afterwards: staging is
empty and the scene folders hold exactly what was committed before.
"""

from __future__ import annotations

import http.client
import json
import tarfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from tests.api.archives import make_tar, make_zip, tar_with, zip_bomb, zip_with_symlink
from tests.api.support import TINY_CONFIG, LiveServer, multipart, store_files, wait_for


@dataclass
class Ctx:
    server: LiveServer
    c: httpx.Client  # the owner's client
    other: httpx.Client  # a different owner
    anon: httpx.Client  # no key
    open_scene: str  # open, holds transforms_train.json
    ready_scene: str  # committed (valid)
    other_scene: str  # another owner's, ready
    cancelled_job: str  # on ready_scene
    other_job: str  # another owner's
    scene: list[tuple[str, bytes]]

    def new_scene(self, files: list[tuple[str, bytes]] | None = None) -> str:
        sid = self.c.post("/v1/scenes", json={"name": "case"}).json()["id"]
        if files:
            r = self.c.post(f"/v1/scenes/{sid}/files", files=multipart(files))
            assert r.status_code == 201, r.text
        return sid


@pytest.fixture(scope="module")
def ctx(server: LiveServer, scene) -> Ctx:
    c = server.client(server.new_key("bad-owner"))
    other = server.client(server.new_key("other-owner"))
    anon = server.client(None)

    def ready(client: httpx.Client) -> str:
        sid = client.post("/v1/scenes", json={"name": "ok"}).json()["id"]
        assert client.post(f"/v1/scenes/{sid}/files", files=multipart(scene)).status_code == 201
        assert client.post(f"/v1/scenes/{sid}/commit").status_code == 200
        return sid

    open_scene = c.post("/v1/scenes", json={"name": "open"}).json()["id"]
    c.post(f"/v1/scenes/{open_scene}/files", files=multipart(scene[-1:]))
    ready_scene, other_scene = ready(c), ready(other)
    server.queue.hold()  # jobs made here stay queued until cancelled: no training
    try:
        job = c.post("/v1/jobs", json={"scene_id": ready_scene, "config": TINY_CONFIG}).json()
        other_job = other.post("/v1/jobs", json={"scene_id": other_scene}).json()
        assert c.post(f"/v1/jobs/{job['id']}/cancel").json()["state"] == "cancelled"
        assert other.post(f"/v1/jobs/{other_job['id']}/cancel").json()["state"] == "cancelled"
    finally:
        server.queue.release()  # the runner finds them cancelled and does nothing
    yield Ctx(
        server,
        c,
        other,
        anon,
        open_scene,
        ready_scene,
        other_scene,
        job["id"],
        other_job["id"],
        scene,
    )
    for client in (c, other, anon):
        client.close()


def _transforms(frames: list[dict]) -> bytes:
    return json.dumps({"camera_angle_x": 0.69, "frames": frames}).encode()


def _frame(path: str = "./train/r_0", matrix: list | None = None) -> dict:
    eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]
    return {"file_path": path, "transform_matrix": matrix or eye}


def _commit(ctx: Ctx, files: list[tuple[str, bytes]]) -> httpx.Response:
    return ctx.c.post(f"/v1/scenes/{ctx.new_scene(files)}/commit")


def _png(ctx: Ctx) -> bytes:
    return dict(ctx.scene)["train/r_0.png"]


def _raw_multipart(body: bytes, boundary: str = "XyZ") -> dict:
    return {
        "content": body,
        "headers": {"Content-Type": f"multipart/form-data; boundary={boundary}"},
    }


def _archive(ctx: Ctx, data: bytes, ctype: str = "application/zip") -> httpx.Response:
    sid = ctx.new_scene()
    return ctx.c.post(f"/v1/scenes/{sid}/archive", content=data, headers={"Content-Type": ctype})


def _declared_length(ctx: Ctx, path: str, length: int) -> httpx.Response:
    """A request announcing ``length`` bytes and sending one (httpx refuses to lie)."""
    conn = http.client.HTTPConnection("127.0.0.1", ctx.server.port, timeout=30)
    try:
        conn.putrequest("POST", path)
        conn.putheader("Authorization", ctx.c.headers["Authorization"])
        conn.putheader("Content-Type", "multipart/form-data; boundary=XyZ")
        conn.putheader("Content-Length", str(length))
        conn.endheaders(b"-")
        r = conn.getresponse()
        return httpx.Response(r.status, headers=r.getheaders(), content=r.read())
    finally:
        conn.close()


def _tar_many(n: int) -> bytes:
    return make_tar([(f"f{i}.txt", b"x") for i in range(n)])


Call = Callable[[Ctx], httpx.Response]
CASES: dict[str, tuple[Call, int, str]] = {
    # --- auth ------------------------------------------------------------------------
    "missing key": (lambda x: x.anon.get("/v1/scenes"), 401, "missing API key"),
    "invalid key": (
        lambda x: x.anon.get("/v1/scenes", headers={"Authorization": "Bearer glk_nope"}),
        401,
        "invalid or revoked",
    ),
    "basic auth instead of bearer": (
        lambda x: x.anon.get("/v1/jobs", headers={"Authorization": "Basic dXNlcjpwdw=="}),
        401,
        "missing API key",
    ),
    # --- JSON bodies -----------------------------------------------------------------
    "malformed JSON": (
        lambda x: x.c.post(
            "/v1/scenes", content=b'{"name": ', headers={"Content-Type": "application/json"}
        ),
        400,
        "not valid JSON",
    ),
    "JSON body with wrong content type": (
        lambda x: x.c.post(
            "/v1/scenes", content=b'{"name": "a"}', headers={"Content-Type": "text/plain"}
        ),
        415,
        "expected an application/json body",
    ),
    "missing required field": (lambda x: x.c.post("/v1/scenes", json={}), 422, "body.name"),
    "unknown field": (
        lambda x: x.c.post("/v1/scenes", json={"name": "a", "colour": "red"}),
        422,
        "body.colour",
    ),
    "name with slashes": (
        lambda x: x.c.post("/v1/scenes", json={"name": "../x"}),
        422,
        "body.name",
    ),
    # --- multipart uploads -----------------------------------------------------------
    "upload with JSON content type": (
        lambda x: x.c.post(f"/v1/scenes/{x.open_scene}/files", json={"a": 1}),
        415,
        "expected multipart/form-data",
    ),
    "multipart without boundary": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.open_scene}/files",
            content=b"--x\r\n",
            headers={"Content-Type": "multipart/form-data"},
        ),
        400,
        "without a boundary",
    ),
    "truncated multipart": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.open_scene}/files",
            **_raw_multipart(
                b'--XyZ\r\nContent-Disposition: form-data; name="files"; filename="a.txt"\r\n'
                b"\r\npartial data without the closing boundary"
            ),
        ),
        400,
        "ended before its final boundary",
    ),
    "part without filename": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.open_scene}/files",
            **_raw_multipart(
                b'--XyZ\r\nContent-Disposition: form-data; name="note"\r\n\r\nhello\r\n--XyZ--\r\n'
            ),
        ),
        422,
        "is not a file",
    ),
    "no parts at all": (
        lambda x: x.c.post(f"/v1/scenes/{x.open_scene}/files", **_raw_multipart(b"--XyZ--\r\n")),
        422,
        "carries no files",
    ),
    "path traversal in filename": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.open_scene}/files", files=multipart([("../../evil.json", b"{}")])
        ),
        422,
        "'..' in path",
    ),
    "absolute filename": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.open_scene}/files", files=multipart([("/etc/passwd", b"x")])
        ),
        422,
        "absolute path",
    ),
    "backslash filename": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.open_scene}/files", files=multipart([("a\\b.png", b"x")])
        ),
        422,
        "backslash",
    ),
    "same file twice in one request": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.open_scene}/files", files=multipart([("a.txt", b"1"), ("a.txt", b"2")])
        ),
        422,
        "appears twice",
    ),
    "oversized file": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.open_scene}/files",
            files=multipart([("ok.txt", b"fine"), ("big.bin", bytes(600 * 1024))]),
        ),
        413,
        "'big.bin' is over the limit",
    ),
    "oversized declared body": (
        lambda x: _declared_length(x, f"/v1/scenes/{x.open_scene}/files", 1 << 40),
        413,
        "over the limit",
    ),
    "too many files": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.open_scene}/files",
            files=multipart([(f"f{i}.txt", b"x") for i in range(45)]),
        ),
        413,
        "too many files",
    ),
    "file where a folder is": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.open_scene}/files", files=multipart([("transforms_train.json/x", b"x")])
        ),
        409,
        "both a file and a folder",
    ),
    "upload after commit": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.ready_scene}/files", files=multipart([("late.txt", b"x")])
        ),
        409,
        "is committed",
    ),
    "upload to unknown scene": (
        lambda x: x.c.post("/v1/scenes/scn_nope/files", files=multipart([("a.txt", b"x")])),
        404,
        "scene 'scn_nope' not found",
    ),
    "upload to another owner's scene": (
        lambda x: x.c.post(f"/v1/scenes/{x.other_scene}/files", files=multipart([("a.txt", b"x")])),
        404,
        "not found",
    ),
    # --- archives --------------------------------------------------------------------
    "zip with ../": (
        lambda x: _archive(x, make_zip([("ok.json", b"{}"), ("../escape.json", b"{}")])),
        422,
        "'..' in path",
    ),
    "absolute path in zip": (
        lambda x: _archive(x, make_zip([("/tmp/abs.json", b"{}")])),
        422,
        "absolute path",
    ),
    "symlink in zip": (lambda x: _archive(x, zip_with_symlink()), 422, "symbolic link"),
    "symlink in tar": (
        lambda x: _archive(x, tar_with(tarfile.SYMTYPE), "application/x-tar"),
        422,
        "is a symbolic link",
    ),
    "hard link in tar": (
        lambda x: _archive(x, tar_with(tarfile.LNKTYPE), "application/x-tar"),
        422,
        "is a hard link",
    ),
    "device in tar": (
        lambda x: _archive(x, tar_with(tarfile.CHRTYPE), "application/x-tar"),
        422,
        "not a regular file",
    ),
    "zip bomb": (lambda x: _archive(x, zip_bomb()), 413, "zip bomb"),
    "too many files in archive": (
        lambda x: _archive(x, _tar_many(45), "application/gzip"),
        413,
        "more than 40 files",
    ),
    "archive over the size limit": (
        lambda x: _archive(x, bytes(3 << 20), "application/zip"),
        413,
        "over the limit",
    ),
    "not an archive": (
        lambda x: _archive(x, b"hello, this is not a zip", "application/zip"),
        422,
        "not a zip or tar",
    ),
    "truncated zip": (
        lambda x: _archive(x, make_zip([("a.json", bytes(5000))])[:60]),
        422,
        "corrupt",
    ),
    "archive with wrong content type": (
        lambda x: _archive(x, make_zip([("a.json", b"{}")]), "text/plain"),
        415,
        "expected an archive",
    ),
    "archive after commit": (
        lambda x: x.c.post(
            f"/v1/scenes/{x.ready_scene}/archive",
            content=make_zip([("a.json", b"{}")]),
            headers={"Content-Type": "application/zip"},
        ),
        409,
        "is committed",
    ),
    # --- validation (commit) -----------------------------------------------------------
    "unknown scene format": (
        lambda x: _commit(x, [("notes.txt", b"hello"), ("img/a.png", _png(x))]),
        422,
        "no known scene format",
    ),
    "missing images": (
        lambda x: _commit(x, [("transforms_train.json", _transforms([_frame()]))]),
        422,
        "train/r_0",
    ),
    "corrupt image bytes": (
        lambda x: _commit(
            x,
            [
                ("transforms_train.json", _transforms([_frame()])),
                ("train/r_0.png", b"\x89PNG\r\n\x1a\n garbage"),
            ],
        ),
        422,
        "train/r_0.png",
    ),
    "NaN in poses": (
        lambda x: _commit(
            x,
            [
                (
                    "transforms_train.json",
                    _transforms([_frame(matrix=[[float("nan")] * 4] * 4)]),
                ),
                ("train/r_0.png", _png(x)),
            ],
        ),
        422,
        "NaN",
    ),
    "malformed transforms JSON": (
        lambda x: _commit(x, [("transforms_train.json", b'{"frames": [')]),
        422,
        "transforms_train.json",
    ),
    "commit with no files": (
        lambda x: x.c.post(f"/v1/scenes/{x.new_scene()}/commit"),
        422,
        "no files",
    ),
    "commit twice": (lambda x: x.c.post(f"/v1/scenes/{x.ready_scene}/commit"), 409, "is committed"),
    "unknown scene id": (lambda x: x.c.get("/v1/scenes/scn_missing"), 404, "not found"),
    "another owner's scene": (lambda x: x.c.get(f"/v1/scenes/{x.other_scene}"), 404, "not found"),
    "delete another owner's scene": (
        lambda x: x.c.delete(f"/v1/scenes/{x.other_scene}"),
        404,
        "not found",
    ),
    "delete a scene with jobs": (
        lambda x: x.c.delete(f"/v1/scenes/{x.ready_scene}"),
        409,
        "delete them first",
    ),
    # --- jobs ----------------------------------------------------------------------------
    "invalid config value": (
        lambda x: x.c.post(
            "/v1/jobs", json={"scene_id": x.ready_scene, "config": {"iterations": 0}}
        ),
        422,
        "body.config.iterations",
    ),
    "invalid nested config value": (
        lambda x: x.c.post(
            "/v1/jobs", json={"scene_id": x.ready_scene, "config": {"loss": {"l1": 3}}}
        ),
        422,
        "body.config.loss.l1",
    ),
    "unknown config field": (
        lambda x: x.c.post(
            "/v1/jobs", json={"scene_id": x.ready_scene, "config": {"learning_speed": 2}}
        ),
        422,
        "body.config.learning_speed",
    ),
    "config value of the wrong type": (
        lambda x: x.c.post(
            "/v1/jobs", json={"scene_id": x.ready_scene, "config": {"iterations": "many"}}
        ),
        422,
        "body.config.iterations",
    ),
    "unknown device": (
        lambda x: x.c.post(
            "/v1/jobs", json={"scene_id": x.ready_scene, "config": {"device": "tpu"}}
        ),
        422,
        "body.config.device",
    ),
    "job on an uncommitted scene": (
        lambda x: x.c.post("/v1/jobs", json={"scene_id": x.open_scene}),
        409,
        "commit it",
    ),
    "job on an unknown scene": (
        lambda x: x.c.post("/v1/jobs", json={"scene_id": "scn_nope"}),
        404,
        "not found",
    ),
    "job on another owner's scene": (
        lambda x: x.c.post("/v1/jobs", json={"scene_id": x.other_scene}),
        404,
        "not found",
    ),
    "unknown job id": (lambda x: x.c.get("/v1/jobs/job_missing"), 404, "job 'job_missing'"),
    "another owner's job": (lambda x: x.c.get(f"/v1/jobs/{x.other_job}"), 404, "not found"),
    "cancel another owner's job": (
        lambda x: x.c.post(f"/v1/jobs/{x.other_job}/cancel"),
        404,
        "not found",
    ),
    "cancel of a finished job": (
        lambda x: x.c.post(f"/v1/jobs/{x.cancelled_job}/cancel"),
        409,
        "already cancelled",
    ),
    "events of an unknown job": (
        lambda x: x.c.get("/v1/jobs/job_missing/events"),
        404,
        "not found",
    ),
    "bad state filter": (lambda x: x.c.get("/v1/jobs?state=sleeping"), 422, "state"),
    "page size zero": (lambda x: x.c.get("/v1/jobs?limit=0"), 422, "limit"),
    "negative offset": (lambda x: x.c.get("/v1/scenes?offset=-1"), 422, "offset"),
    # --- artifacts and routing -------------------------------------------------------------
    "unknown artifact": (
        lambda x: x.c.get(f"/v1/jobs/{x.cancelled_job}/artifacts/nope.ply"),
        404,
        "not found",
    ),
    "artifacts of another owner's job": (
        lambda x: x.c.get(f"/v1/jobs/{x.other_job}/artifacts"),
        404,
        "not found",
    ),
    "unknown route": (lambda x: x.c.get("/v1/teapots"), 404, "no route"),
    "wrong method": (lambda x: x.c.put("/v1/scenes"), 405, "PUT is not allowed"),
}


@pytest.mark.parametrize("case", list(CASES), ids=list(CASES))
def test_bad_input(ctx: Ctx, case: str) -> None:
    call, status, needle = CASES[case]
    before = _scene_files(ctx, ctx.open_scene)
    r = call(ctx)
    assert r.status_code == status, f"{case}: {r.status_code} {r.text}"
    assert r.headers["content-type"] == "application/problem+json", r.headers
    body = r.json()
    assert body["status"] == status
    assert body["type"].startswith("urn:glint:problem:")
    assert body["title"] and body["instance"].startswith("/v1/")
    text = body.get("detail", "") + json.dumps(body.get("errors") or [])
    assert needle in text, f"{case}: {needle!r} not in {text!r}"
    assert str(ctx.server.settings.store_root) not in text, "server paths leaked"
    # nothing half-written: staging is empty and the open scene is unchanged
    files = store_files(ctx.server.settings.store_root)
    assert not [f for f in files if f.startswith("tmp/")], files
    assert _scene_files(ctx, ctx.open_scene) == before


def _scene_files(ctx: Ctx, scene_id: str) -> list[str]:
    root = Path(ctx.server.settings.store_root) / "scenes" / scene_id / "files"
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())


def test_failed_commit_names_file_and_field(ctx: Ctx) -> None:
    """The scene error's file and field reach the client, and the scene re-opens."""
    frames = [_frame(matrix=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, "x"], [0, 0, 0, 1]])]
    sid = ctx.new_scene([("transforms_train.json", _transforms(frames))])
    r = ctx.c.post(f"/v1/scenes/{sid}/commit")
    assert r.status_code == 422
    err = r.json()["errors"][0]
    assert err["file"] == "transforms_train.json"
    assert err["field"].startswith("frames[0]")
    scene = ctx.c.get(f"/v1/scenes/{sid}").json()
    assert scene["state"] == "open"
    assert scene["last_error"]["errors"][0]["file"] == "transforms_train.json"
    # fixing the file and committing again works
    assert ctx.c.post(f"/v1/scenes/{sid}/files", files=multipart(ctx.scene)).status_code == 201
    assert ctx.c.post(f"/v1/scenes/{sid}/commit").json()["state"] == "ready"


def test_no_5xx_for_garbage_bodies(ctx: Ctx) -> None:
    """Random bytes at every body-taking route answer 4xx."""
    garbage = bytes(range(256)) * 4
    targets = [
        ("POST", "/v1/scenes"),
        ("POST", "/v1/jobs"),
        ("POST", "/v1/keys"),
        ("POST", f"/v1/scenes/{ctx.open_scene}/files"),
        ("POST", f"/v1/scenes/{ctx.open_scene}/archive"),
    ]
    for ctype in ("application/json", "multipart/form-data; boundary=a", "application/zip"):
        for method, path in targets:
            r = ctx.c.request(method, path, content=garbage, headers={"Content-Type": ctype})
            assert 400 <= r.status_code < 500, (method, path, ctype, r.status_code, r.text)
    assert _scene_files(ctx, ctx.open_scene) == ["transforms_train.json"]


def test_revoked_key_is_refused(server: LiveServer) -> None:
    key = server.new_key("revoker")
    with server.client(key) as c:
        me = c.get("/v1/keys/me").json()
        assert c.delete(f"/v1/keys/{me['key_id']}").status_code == 204
        r = c.get("/v1/scenes")
        assert r.status_code == 401 and "revoked" in r.json()["detail"]
        assert r.headers["www-authenticate"].startswith("Bearer")


def test_case_count() -> None:
    assert len(CASES) >= 30


def test_client_vanishing_mid_upload_leaves_nothing(ctx: Ctx) -> None:
    """Half a multipart body, then the connection closes: staging is cleaned up."""
    before = _scene_files(ctx, ctx.open_scene)
    head = b'--XyZ\r\nContent-Disposition: form-data; name="files"; filename="half.bin"\r\n\r\n'
    conn = http.client.HTTPConnection("127.0.0.1", ctx.server.port, timeout=30)
    conn.putrequest("POST", f"/v1/scenes/{ctx.open_scene}/files")
    conn.putheader("Authorization", ctx.c.headers["Authorization"])
    conn.putheader("Content-Type", "multipart/form-data; boundary=XyZ")
    conn.putheader("Content-Length", str(len(head) + 300_000))
    conn.endheaders(head + bytes(200_000))
    time.sleep(0.3)  # let the server stage what arrived
    conn.close()
    store = ctx.server.settings.store_root

    def clean() -> bool:
        return not [f for f in store_files(store) if f.startswith("tmp/")]

    wait_for(clean, timeout=10)
    assert _scene_files(ctx, ctx.open_scene) == before
