"""A corpus of bad requests, one per case: each is refused with the right status, a
problem+json body that names the cause (the field, or the archive member), and
nothing written: no new scene, file, job, artifact or key row, no new file in the store.

The cases run against a server of their own (its queue only records ids: no job ever
runs), so nothing else writes to its database or store while they run.
"""

from __future__ import annotations

import json
import tarfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import httpx
import pytest
from sqlalchemy import func, select

from api.service.models import ApiKey, Artifact, Job, Scene, SceneFile
from tests.api.archives import (
    make_tar,
    make_zip,
    tar_of_folder,
    tar_with,
    zip_bomb,
    zip_with_nul,
    zip_with_symlink,
)
from tests.api.support import LiveServer, RecordingQueue, make_settings, multipart


@dataclass
class World:
    server: LiveServer
    admin: httpx.Client  # an admin key of owner 'corpus'
    writer: httpx.Client  # a write key of 'corpus'
    reader: httpx.Client  # a read key of 'corpus'
    revoked: httpx.Client  # a revoked key of 'corpus'
    anon: httpx.Client  # no key
    open_scene: str  # corpus's, open, holds one file
    ready_scene: str  # corpus's, committed
    job: str  # corpus's, queued
    other_scene: str  # stranger's, committed
    other_job: str  # stranger's
    other_key: str  # the id of stranger's key


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory, scene) -> Iterator[World]:
    settings = make_settings(tmp_path_factory.mktemp("corpus"))
    srv = LiveServer(settings, RecordingQueue()).start()
    admin = srv.client(srv.new_key("corpus"))
    keys = {
        scope: admin.post("/v1/keys", json={"name": scope, "scope": scope}).json()
        for scope in ("write", "read")
    }
    gone = admin.post("/v1/keys", json={"name": "gone", "scope": "write"}).json()
    assert admin.delete(f"/v1/keys/{gone['id']}").status_code == 204
    stranger = srv.client(srv.new_key("stranger"))

    def ready(c: httpx.Client) -> str:
        sid = c.post("/v1/scenes", json={"name": "ready"}).json()["id"]
        assert c.post(f"/v1/scenes/{sid}/files", files=multipart(scene)).status_code == 201
        assert c.post(f"/v1/scenes/{sid}/commit").status_code == 200
        return sid

    open_scene = admin.post("/v1/scenes", json={"name": "open"}).json()["id"]
    r = admin.post(f"/v1/scenes/{open_scene}/files", files=multipart(scene[-1:]))
    assert r.status_code == 201
    ready_scene, other_scene = ready(admin), ready(stranger)
    job = admin.post("/v1/jobs", json={"scene_id": ready_scene}).json()["id"]
    other_job = stranger.post("/v1/jobs", json={"scene_id": other_scene}).json()["id"]
    clients = [
        admin,
        srv.client(keys["write"]["key"]),
        srv.client(keys["read"]["key"]),
        srv.client(gone["key"]),
        srv.client(None),
    ]
    other_key = stranger.get("/v1/keys/me").json()["key_id"]
    stranger.close()
    yield World(srv, *clients, open_scene, ready_scene, job, other_scene, other_job, other_key)
    for c in clients:
        c.close()
    srv.stop()
    srv.database.dispose()


Call = Callable[[World], httpx.Response]
Names = Literal["field", "file", "detail"]


@dataclass(frozen=True)
class Case:
    call: Call
    status: int
    names: str  # what the body must name ...
    where: Names = "field"  # ... as errors[].field, errors[].file, or in detail
    type: str | None = None  # the problem type, when it says more than the status


def _json(w: World, path: str, text: str | bytes, client: str = "admin") -> httpx.Response:
    c: httpx.Client = getattr(w, client)
    return c.post(path, content=text, headers={"Content-Type": "application/json"})


def _config(w: World, config: str) -> httpx.Response:
    return _json(w, "/v1/jobs", f'{{"scene_id": "{w.ready_scene}", "config": {config}}}')


def _archive(w: World, data: bytes, ctype: str = "application/zip") -> httpx.Response:
    return w.admin.post(
        f"/v1/scenes/{w.open_scene}/archive", content=data, headers={"Content-Type": ctype}
    )


def _tar(w: World, data: bytes) -> httpx.Response:
    return _archive(w, data, "application/x-tar")


def _raw_part(w: World, filename: bytes) -> httpx.Response:
    body = (
        b'--XyZ\r\nContent-Disposition: form-data; name="files"; filename="'
        + filename
        + b'"\r\n\r\nhello\r\n--XyZ--\r\n'
    )
    return w.admin.post(
        f"/v1/scenes/{w.open_scene}/files",
        content=body,
        headers={"Content-Type": "multipart/form-data; boundary=XyZ"},
    )


def _upload(w: World, name: str) -> httpx.Response:
    return w.admin.post(f"/v1/scenes/{w.open_scene}/files", files=multipart([(name, b"x")]))


DIGITS_5000 = "1" + "0" * 5000
SCENE = [("transforms_train.json", b"{}"), ("train/r_0.png", b"png")]
VALIDATION, UNSAFE, BAD_ARCHIVE = "validation-error", "unsafe-archive", "bad-archive"

CASES: dict[str, Case] = {
    # --- JSON syntax and content type ------------------------------------------------
    "malformed JSON": Case(lambda w: _json(w, "/v1/scenes", '{"name": '), 400, "body"),
    "JSON with trailing garbage": Case(lambda w: _json(w, "/v1/scenes", '{"a": 1} x'), 400, "body"),
    "binary body declared JSON": Case(lambda w: _json(w, "/v1/jobs", b"\x83\xff\x00"), 400, "body"),
    "deeply nested JSON": Case(
        lambda w: _json(w, "/v1/scenes", "[" * 100_000 + "]" * 100_000), 400, "body"
    ),
    "text/plain body": Case(
        lambda w: w.admin.post("/v1/jobs", content=b"{}", headers={"Content-Type": "text/plain"}),
        415,
        "application/json",
        "detail",
    ),
    "no content type": Case(
        lambda w: w.admin.post("/v1/scenes", content=b'{"name": "x"}'),
        415,
        "no content type",
        "detail",
    ),
    # --- JSON fields: wrong types, unknown fields ------------------------------------
    "name of the wrong type": Case(
        lambda w: _json(w, "/v1/scenes", '{"name": 5}'), 422, "body.name"
    ),
    "missing required field": Case(lambda w: _json(w, "/v1/scenes", "{}"), 422, "body.name"),
    "unknown field": Case(
        lambda w: _json(w, "/v1/scenes", '{"name": "a", "colour": 1}'), 422, "body.colour"
    ),
    "body is an array": Case(lambda w: _json(w, "/v1/scenes", "[]"), 422, "body"),
    "iterations of the wrong type": Case(
        lambda w: _config(w, '{"iterations": "many"}'), 422, "body.config.iterations"
    ),
    "unknown config field": Case(
        lambda w: _config(w, '{"learning_speed": 2}'), 422, "body.config.learning_speed"
    ),
    "unknown nested config field": Case(
        lambda w: _config(w, '{"loss": {"colour": 1}}'), 422, "body.config.loss.colour"
    ),
    "unknown device": Case(lambda w: _config(w, '{"device": "tpu"}'), 422, "body.config.device"),
    "scene id in a body too long": Case(
        lambda w: _json(w, "/v1/jobs", '{"scene_id": "' + "s" * 41 + '"}'), 422, "body.scene_id"
    ),
    "unknown key scope": Case(
        lambda w: _json(w, "/v1/keys", '{"name": "k", "scope": "root"}'), 422, "body.scope"
    ),
    # --- numbers: huge, non-finite, out of bounds ------------------------------------
    "iterations 2^63": Case(
        lambda w: _config(w, '{"iterations": 9223372036854775808}'), 422, "body.config.iterations"
    ),
    "iterations 10^30": Case(
        lambda w: _config(w, '{"iterations": 1000000000000000000000000000000}'),
        422,
        "body.config.iterations",
    ),
    "iterations of 5000 digits": Case(
        lambda w: _config(w, f'{{"iterations": {DIGITS_5000}}}'), 422, "body.config.iterations"
    ),
    "negative int below int64": Case(
        lambda w: _config(w, '{"seed": -9223372036854775809}'), 422, "body.config.seed"
    ),
    "iterations over the bound": Case(
        lambda w: _config(w, '{"iterations": 10000001}'), 422, "body.config.iterations"
    ),
    "a trillion initial points": Case(
        lambda w: _config(w, '{"init_points": 1000000000000}'), 422, "body.config.init_points"
    ),
    "a trillion Gaussians": Case(
        lambda w: _config(w, '{"densify": {"max_gaussians": 1000000000000}}'),
        422,
        "body.config.densify.max_gaussians",
    ),
    "a 10^6 env map": Case(
        lambda w: _config(w, '{"envmap_resolution": 1000000}'), 422, "body.config.envmap_resolution"
    ),
    "loss weight Infinity": Case(
        lambda w: _config(w, '{"loss": {"scale": Infinity}}'), 422, "body.config.loss.scale"
    ),
    "loss weight NaN": Case(
        lambda w: _config(w, '{"loss": {"scale": NaN}}'), 422, "body.config.loss.scale"
    ),
    "learning rate -Infinity": Case(
        lambda w: _config(w, '{"lr": {"sh_dc": -Infinity}}'), 422, "body.config.lr.sh_dc"
    ),
    "learning rate overflowing a double": Case(
        lambda w: _config(w, '{"lr": {"means_init": 1e400}}'), 422, "body.config.lr.means_init"
    ),
    "learning rate over the bound": Case(
        lambda w: _config(w, '{"lr": {"means_init": 5.0}}'), 422, "body.config.lr.means_init"
    ),
    "loss weight over the bound": Case(
        lambda w: _config(w, '{"loss": {"single_view": 1e7}}'), 422, "body.config.loss.single_view"
    ),
    "negative seed": Case(lambda w: _config(w, '{"seed": -1}'), 422, "body.config.seed"),
    "huge int deep in plan_overrides": Case(
        lambda w: _config(w, '{"plan_overrides": {"a": [1, 99999999999999999999]}}'),
        422,
        "body.config.plan_overrides.a[1]",
    ),
    "huge mesh resolution": Case(
        lambda w: _json(w, f"/v1/jobs/{w.job}/meshes", '{"resolution": 1e400}'),
        422,
        "body.resolution",
    ),
    "mesh keep_fraction out of bounds": Case(
        lambda w: _json(w, f"/v1/jobs/{w.job}/meshes", '{"keep_fraction": 2}'),
        422,
        "body.keep_fraction",
    ),
    # --- archives ----------------------------------------------------------------------
    "zip slip": Case(
        lambda w: _archive(w, make_zip([*SCENE, ("../escape.json", b"{}")])),
        422,
        "../escape.json",
        "file",
        UNSAFE,
    ),
    "absolute path in zip": Case(
        lambda w: _archive(w, make_zip([("/tmp/abs.json", b"{}")])),
        422,
        "/tmp/abs.json",
        "file",
        UNSAFE,
    ),
    "NUL in a zip member name": Case(
        lambda w: _archive(w, zip_with_nul()), 422, "evil.json\\x00.png", "file", UNSAFE
    ),
    "symlink in zip": Case(
        lambda w: _archive(w, zip_with_symlink()), 422, "train/r_0.png", "file", UNSAFE
    ),
    "symlink in tar": Case(
        lambda w: _tar(w, tar_with(tarfile.SYMTYPE)), 422, "train/r_0.png", "file", UNSAFE
    ),
    "symlink out of a dot tar": Case(
        lambda w: _tar(w, tar_with(tarfile.SYMTYPE, name="./link", linkname="../../..")),
        422,
        "./link",
        "file",
        UNSAFE,
    ),
    "hard link in tar": Case(
        lambda w: _tar(w, tar_with(tarfile.LNKTYPE)), 422, "train/r_0.png", "file", UNSAFE
    ),
    "device in tar": Case(
        lambda w: _tar(w, tar_with(tarfile.CHRTYPE)), 422, "train/r_0.png", "file", UNSAFE
    ),
    ".. in a dot tar": Case(
        lambda w: _archive(w, tar_of_folder([*SCENE, ("../x.json", b"{}")]), "application/gzip"),
        422,
        "./..",
        "file",
        UNSAFE,
    ),
    ".. member in tar": Case(
        lambda w: _archive(w, make_tar([*SCENE, ("./../x.json", b"{}")]), "application/gzip"),
        422,
        "./../x.json",
        "file",
        UNSAFE,
    ),
    ".. folder in tar": Case(
        lambda w: _tar(w, tar_with(tarfile.DIRTYPE, name="a/../..")),
        422,
        "a/../..",
        "file",
        UNSAFE,
    ),
    "absolute path in tar": Case(
        lambda w: _archive(w, make_tar([("/etc/x.json", b"{}")]), "application/gzip"),
        422,
        "/etc/x.json",
        "file",
        UNSAFE,
    ),
    "duplicate member": Case(
        lambda w: _archive(w, make_zip([("a.json", b"1"), ("./a.json", b"2")])),
        422,
        "./a.json",
        "file",
        UNSAFE,
    ),
    "empty zip": Case(lambda w: _archive(w, make_zip([])), 422, "no files", "detail", BAD_ARCHIVE),
    "empty tar": Case(
        lambda w: _archive(w, make_tar([]), "application/gzip"),
        422,
        "no files",
        "detail",
        BAD_ARCHIVE,
    ),
    "archive of folders only": Case(
        lambda w: _tar(w, tar_of_folder([])), 422, "no files", "detail", BAD_ARCHIVE
    ),
    "not an archive": Case(
        lambda w: _archive(w, b"hello, not a zip"), 422, "not a zip or tar", "detail", BAD_ARCHIVE
    ),
    "truncated zip": Case(
        lambda w: _archive(w, make_zip([("a.json", bytes(5000))])[:60]),
        422,
        "corrupt",
        "detail",
        BAD_ARCHIVE,
    ),
    "archive as text/plain": Case(
        lambda w: _archive(w, make_zip(SCENE), "text/plain"), 415, "expected an archive", "detail"
    ),
    "zip bomb": Case(lambda w: _archive(w, zip_bomb()), 413, "zeros.bin", "detail", "too-large"),
    # --- multipart file names ----------------------------------------------------------
    "path traversal in a file name": Case(
        lambda w: _upload(w, "../../evil.json"), 422, "body.files.filename", type="unsafe-path"
    ),
    "absolute file name": Case(
        lambda w: _upload(w, "/etc/passwd"), 422, "body.files.filename", type="unsafe-path"
    ),
    "NUL in a file name": Case(
        lambda w: _raw_part(w, b"a\x00b.txt"), 422, "body.files.filename", type="unsafe-path"
    ),
    # --- queries and cursors -------------------------------------------------------------
    "page size zero": Case(lambda w: w.admin.get("/v1/jobs?limit=0"), 422, "query.limit"),
    "page size not a number": Case(lambda w: w.admin.get("/v1/keys?limit=ten"), 422, "query.limit"),
    "negative offset": Case(lambda w: w.admin.get("/v1/scenes?offset=-1"), 422, "query.offset"),
    "offset past 2^31": Case(
        lambda w: w.admin.get(f"/v1/jobs/{w.job}/artifacts?offset=99999999999"),
        422,
        "query.offset",
    ),
    "offset not an integer": Case(
        lambda w: w.admin.get(f"/v1/scenes/{w.open_scene}/files?offset=1.5"), 422, "query.offset"
    ),
    "unknown state filter": Case(
        lambda w: w.admin.get("/v1/jobs?state=sleeping"), 422, "query.state[0]"
    ),
    "unknown kind filter": Case(lambda w: w.admin.get("/v1/jobs?kind=video"), 422, "query.kind"),
    # --- ids -------------------------------------------------------------------------------
    "job id too long": Case(lambda w: w.admin.get("/v1/jobs/" + "j" * 41), 422, "path.job_id"),
    "scene id too long": Case(
        lambda w: w.admin.delete("/v1/scenes/" + "s" * 41), 422, "path.scene_id"
    ),
    "unknown job id": Case(lambda w: w.admin.get("/v1/jobs/job_nope"), 404, "job_nope", "detail"),
    "unknown scene id": Case(
        lambda w: w.admin.post("/v1/scenes/scn_nope/commit"), 404, "scn_nope", "detail"
    ),
    "another owner's job": Case(
        lambda w: w.admin.get(f"/v1/jobs/{w.other_job}"), 404, "not found", "detail"
    ),
    "cancel another owner's job": Case(
        lambda w: w.admin.post(f"/v1/jobs/{w.other_job}/cancel"), 404, "not found", "detail"
    ),
    "upload to another owner's scene": Case(
        lambda w: w.admin.post(
            f"/v1/scenes/{w.other_scene}/files", files=multipart([("a.txt", b"x")])
        ),
        404,
        "not found",
        "detail",
    ),
    "train on another owner's scene": Case(
        lambda w: w.admin.post("/v1/jobs", json={"scene_id": w.other_scene}),
        404,
        "not found",
        "detail",
    ),
    "mesh another owner's job": Case(
        lambda w: w.admin.post(f"/v1/jobs/{w.other_job}/meshes", json={}),
        404,
        "not found",
        "detail",
    ),
    "revoke another owner's key": Case(
        lambda w: w.admin.delete(f"/v1/keys/{w.other_key}"), 404, "not found", "detail"
    ),
    # --- auth and scopes ---------------------------------------------------------------------
    "missing key": Case(lambda w: w.anon.get("/v1/scenes"), 401, "header.authorization"),
    "malformed key": Case(
        lambda w: w.anon.get("/v1/jobs", headers={"Authorization": "Bearer nope"}),
        401,
        "header.authorization",
    ),
    "basic auth": Case(
        lambda w: w.anon.get("/v1/jobs", headers={"Authorization": "Basic dXNlcjpwdw=="}),
        401,
        "header.authorization",
    ),
    "revoked key": Case(lambda w: w.revoked.get("/v1/keys/me"), 401, "header.authorization"),
    "revoked key writing": Case(
        lambda w: w.revoked.post("/v1/scenes", json={"name": "x"}), 401, "header.authorization"
    ),
    "read key creates a scene": Case(
        lambda w: w.reader.post("/v1/scenes", json={"name": "x"}),
        403,
        "header.authorization",
        type="insufficient-scope",
    ),
    "read key uploads": Case(
        lambda w: w.reader.post(
            f"/v1/scenes/{w.open_scene}/files", files=multipart([("a.txt", b"x")])
        ),
        403,
        "header.authorization",
        type="insufficient-scope",
    ),
    "read key uploads an archive": Case(
        lambda w: w.reader.post(
            f"/v1/scenes/{w.open_scene}/archive",
            content=make_zip(SCENE),
            headers={"Content-Type": "application/zip"},
        ),
        403,
        "header.authorization",
        type="insufficient-scope",
    ),
    "read key trains": Case(
        lambda w: w.reader.post("/v1/jobs", json={"scene_id": w.ready_scene}),
        403,
        "header.authorization",
        type="insufficient-scope",
    ),
    "read key deletes a scene": Case(
        lambda w: w.reader.delete(f"/v1/scenes/{w.open_scene}"),
        403,
        "header.authorization",
        type="insufficient-scope",
    ),
    "write key creates a key": Case(
        lambda w: w.writer.post("/v1/keys", json={"name": "x"}),
        403,
        "header.authorization",
        type="insufficient-scope",
    ),
    # --- routing -------------------------------------------------------------------------------
    "unknown route": Case(lambda w: w.admin.get("/v1/teapots"), 404, "/v1/teapots", "detail"),
    "wrong method": Case(lambda w: w.admin.put("/v1/scenes"), 405, "GET, POST", "detail"),
}


def _rows(w: World) -> dict[str, int]:
    with w.server.database.read() as s:
        return {
            t.__name__: int(s.scalar(select(func.count()).select_from(t)) or 0)
            for t in (Scene, SceneFile, Job, Artifact, ApiKey)
        }


def _store(w: World) -> list[tuple[str, int]]:
    root = Path(w.server.settings.store_root)
    files = (p for p in root.rglob("*") if p.is_file())
    return sorted((p.relative_to(root).as_posix(), p.stat().st_size) for p in files)


def test_the_corpus_is_large() -> None:
    assert len(CASES) >= 50


@pytest.mark.parametrize("name", list(CASES), ids=list(CASES))
def test_bad_request(world: World, name: str) -> None:
    case = CASES[name]
    rows, store = _rows(world), _store(world)
    r = case.call(world)
    assert r.status_code == case.status, f"{name}: {r.status_code} {r.text[:500]}"
    assert r.headers["content-type"] == "application/problem+json", r.headers
    body = r.json()
    assert body["status"] == case.status and body["title"] and body["detail"]
    assert body["type"].startswith("urn:glint:problem:")
    if case.type:
        assert body["type"] == f"urn:glint:problem:{case.type}", body
    errors = body.get("errors") or []
    if case.where == "detail":
        assert case.names in body["detail"], f"{name}: {case.names!r} not in {body['detail']!r}"
    else:
        named = [e.get(case.where) for e in errors]
        assert case.names in named, f"{name}: {case.names!r} not among {case.where}s {named}"
    text = json.dumps(body)
    assert str(world.server.settings.store_root) not in text, "server paths leaked"
    # nothing written: no row, no file (staging included), no file changed in size
    assert _rows(world) == rows, name
    assert _store(world) == store, name
