"""Meshes through the API alone: every job ends with one; re-extraction on request.

Real uvicorn, real runner (the queue double runs ``run_job`` on threads, as the
embedded queue does); the Celery path is in ``tests/worker/test_celery.py``.
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tests.api.support import TINY_CONFIG, LiveServer, list_all, multipart, wait_for

TERMINAL = ("succeeded", "failed", "cancelled")


def _ready_scene(c, scene) -> str:  # type: ignore[no-untyped-def]
    r = c.post("/v1/scenes", json={"name": "mesh me"})
    sid = r.json()["id"]
    assert c.post(f"/v1/scenes/{sid}/files", files=multipart(scene)).status_code == 201
    assert c.post(f"/v1/scenes/{sid}/commit").json()["state"] == "ready"
    return sid


def _finished(c, job_id: str, timeout: float = 180) -> dict:  # type: ignore[no-untyped-def]
    def done() -> dict | None:
        j = c.get(f"/v1/jobs/{job_id}").json()
        return j if j["state"] in TERMINAL else None

    return wait_for(done, timeout=timeout, every=0.2)


def _load(c, job_id: str, name: str) -> trimesh.Trimesh:  # type: ignore[no-untyped-def]
    r = c.get(f"/v1/jobs/{job_id}/artifacts/{name}")
    assert r.status_code == 200, r.text
    return trimesh.load(io.BytesIO(r.content), file_type=name.rsplit(".", 1)[1], force="mesh")


def _check_mesh(mesh: trimesh.Trimesh, *, normals: bool) -> None:
    assert len(mesh.faces) > 50
    assert mesh.visual.kind == "vertex"
    vc = np.asarray(mesh.visual.vertex_colors)[:, :3]
    assert vc.std() > 0 or vc.mean() > 0  # coloured, not the default grey of no colour
    # the synthetic sphere (r = 0.6) sits at the origin, inside the scene's box
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert r.max() < 1.2
    if normals:
        assert "vertex_normals" in mesh._cache or len(mesh.vertex_normals) == len(mesh.vertices)


TRAIN_ASSET = {"asset": True, "asset_faces": 1000, "asset_texture_size": 64}
ASSET_TYPES = {
    "asset.glb": "model/gltf-binary",
    "asset.json": "application/json",
    "asset_env.hdr": "image/vnd.radiance",
    "asset_env.exr": "image/x-exr",
    "asset_preview.png": "image/png",
}


@pytest.fixture(scope="module")
def trained(server: LiveServer, scene, tmp_path_factory) -> tuple[str, str]:  # type: ignore[no-untyped-def]
    """(key, job id) of one finished tiny job with the default outputs (mesh on) and a
    tiny relightable asset (outputs.asset: the training job's config carries it)."""
    key = server.new_key("mesh-owner")
    outputs = {**TINY_CONFIG["outputs"], **TRAIN_ASSET}
    with server.client(key) as c:
        sid = _ready_scene(c, scene)
        r = c.post(
            "/v1/jobs", json={"scene_id": sid, "config": {**TINY_CONFIG, "outputs": outputs}}
        )
        assert r.status_code == 201, r.text
        job = _finished(c, r.json()["id"])
        assert job["state"] == "succeeded", job["error"]
    return key, job["id"]


def test_a_training_job_ends_with_a_coloured_mesh(server: LiveServer, trained) -> None:  # type: ignore[no-untyped-def]
    key, job_id = trained
    with server.client(key) as c:
        job = c.get(f"/v1/jobs/{job_id}").json()
        assert job["kind"] == "train" and job["plan"]["decisions"]["mesh"]["value"] is True
        assert job["stage"]["name"] == "asset"  # the last step after training: mesh, asset
        arts = {a["name"]: a for a in list_all(c, f"/v1/jobs/{job_id}/artifacts")}
        for name, ctype in (
            ("mesh.ply", "application/x-ply"),
            ("mesh.glb", "model/gltf-binary"),
            ("mesh.obj", "model/obj"),
            ("mesh_preview.png", "image/png"),
        ):
            assert arts[name]["content_type"] == ctype
            body = c.get(arts[name]["url"]).content
            assert len(body) == arts[name]["size"] > 0
            assert hashlib.sha256(body).hexdigest() == arts[name]["sha256"]
        _check_mesh(_load(c, job_id, "mesh.ply"), normals=True)
        _check_mesh(_load(c, job_id, "mesh.glb"), normals=False)
        info = json.loads(c.get(f"/v1/jobs/{job_id}/artifacts/mesh.json").content)
        assert info["color"] == "base" and info["faces"] > 50
        report = c.get(f"/v1/jobs/{job_id}/artifacts/report.md").text
        assert "## Mesh" in report and "mesh_preview.png" in report
        assert not any(n.endswith(".tmp") or "staging" in n for n in arts)
        # outputs.asset: the asset files after the mesh, with their content types
        assert job["config"]["outputs"]["asset"] is True
        for name, ctype in ASSET_TYPES.items():
            assert arts[name]["content_type"] == ctype, name
        info = json.loads(c.get(f"/v1/jobs/{job_id}/artifacts/asset.json").content)
        assert info["textures"]["size"] == 64 and info["mesh"]["faces"] <= 1050


def test_mesh_outputs_can_be_switched_off(server: LiveServer, scene) -> None:  # type: ignore[no-untyped-def]
    with server.client(server.new_key("no-mesh-owner")) as c:
        sid = _ready_scene(c, scene)
        cfg = {**TINY_CONFIG, "iterations": 6, "outputs": {"mesh": False}}
        job = _finished(c, c.post("/v1/jobs", json={"scene_id": sid, "config": cfg}).json()["id"])
        assert job["state"] == "succeeded", job["error"]
        names = {a["name"] for a in list_all(c, f"/v1/jobs/{job['id']}/artifacts")}
        assert "point_cloud.ply" in names and not {"mesh.ply", "mesh.glb"} & names
        assert job["plan"]["decisions"]["mesh"]["value"] is False


def test_reextraction_with_radiance_colour_and_listing(server: LiveServer, trained) -> None:  # type: ignore[no-untyped-def]
    key, job_id = trained
    with server.client(key) as c:
        r = c.post(
            f"/v1/jobs/{job_id}/meshes",
            json={
                "resolution": 40, "color": "radiance", "keep_fraction": 0.0, "simplify": 200,
                "grazing_blend": False,
            },
        )  # fmt: skip
        assert r.status_code == 201, r.text
        mesh_job = r.json()
        assert mesh_job["kind"] == "mesh" and mesh_job["parent_id"] == job_id
        done = _finished(c, mesh_job["id"])
        assert done["state"] == "succeeded", done["error"]
        assert done["progress"] == 1.0 and done["phase"] == "mesh"
        info = json.loads(c.get(f"/v1/jobs/{done['id']}/artifacts/mesh.json").content)
        assert info["color"] == "radiance" and info["fusion"]["shape"][0] <= 41
        assert info["grazing_blend_cos"] is None  # planar depth at every angle, as asked
        mesh = _load(c, done["id"], "mesh.ply")
        assert len(mesh.faces) <= 220  # simplified to about 200 faces
        listed = c.get(f"/v1/jobs/{job_id}/meshes").json()
        assert done["id"] in [m["id"] for m in listed["items"]]
        assert all(m["parent_id"] == job_id for m in listed["items"])
        # only mesh jobs when asked
        kinds = {j["kind"] for j in c.get("/v1/jobs", params={"kind": "mesh"}).json()["items"]}
        assert kinds == {"mesh"}


def test_a_mesh_job_with_an_asset_lists_its_files(server: LiveServer, trained) -> None:  # type: ignore[no-untyped-def]
    """The asset is baked from the mesh this job made (its simplification, not the
    parent's mesh), its files are the job's artifacts with their content types, and the
    job's progress ends at 1 in the asset stage."""
    key, job_id = trained
    body = {
        "resolution": 32,
        "simplify": 1500,
        "asset": {"faces": 1000, "texture_size": 64, "views": 2},
    }
    with server.client(key) as c:
        r = c.post(f"/v1/jobs/{job_id}/meshes", json=body)
        assert r.status_code == 201, r.text
        assert r.json()["config"]["asset"] == {**body["asset"], "occlusion": True}
        done = _finished(c, r.json()["id"])
        assert done["state"] == "succeeded", done["error"]
        assert done["progress"] == 1.0 and done["phase"] == "asset"
        arts = {a["name"]: a for a in list_all(c, f"/v1/jobs/{done['id']}/artifacts")}
        assert {"mesh.ply", "mesh.glb", "mesh.json"} <= set(arts)
        for name, ctype in ASSET_TYPES.items():  # the glossy sphere's plan has an env map
            assert arts[name]["content_type"] == ctype, name
        glb = c.get(arts["asset.glb"]["url"])
        assert glb.headers["content-type"] == "model/gltf-binary"
        assert glb.content[:4] == b"glTF" and len(glb.content) == arts["asset.glb"]["size"]
        assert c.get(arts["asset_env.hdr"]["url"]).content.startswith(b"#?")
        info = c.get(arts["asset.json"]["url"]).json()
        mesh_info = c.get(arts["mesh.json"]["url"]).json()
        assert info["mesh"]["source_faces"] == mesh_info["faces"] <= 1600
        assert info["textures"]["size"] == 64 and info["environment"]["present"] is True


def test_mesh_and_asset_progress_only_grows() -> None:
    """The mesh fills the first half of a mesh+asset job's count, the asset the second."""
    from api.service.runner import _StageChain

    seen: list[tuple[int, int]] = []
    chain = _StageChain(lambda e: seen.append((e["overall_done"], e["overall_total"])))
    for done in range(0, 11):
        chain.first({"type": "stage", "name": "mesh", "overall_done": done, "overall_total": 10})
    for done in range(0, 7):
        chain.second({"type": "stage", "name": "asset", "overall_done": done, "overall_total": 6})
    assert {total for _, total in seen} == {20}
    dones = [d for d, _ in seen]
    assert dones == sorted(dones) and dones[0] == 0 and dones[-1] == 20


def test_a_failed_asset_keeps_the_mesh_and_says_why(
    server: LiveServer, trained, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    import core.asset.export as export_mod
    from core.errors import AssetError

    def failing(model, views, out, mesh, **kw):  # type: ignore[no-untyped-def]
        (out / "asset.glb").write_bytes(b"glTF half")  # a half-written file is removed
        raise AssetError("could not simplify the mesh from 10 to about 1000 faces")

    monkeypatch.setattr(export_mod, "export_asset", failing)
    key, job_id = trained
    with server.client(key) as c:
        r = c.post(f"/v1/jobs/{job_id}/meshes", json={"resolution": 32, "asset": {}})
        done = _finished(c, r.json()["id"])
        assert done["state"] == "failed"
        assert "the asset is not: could not simplify the mesh" in done["error"], done["error"]
        names = {a["name"] for a in list_all(c, f"/v1/jobs/{done['id']}/artifacts")}
        assert {"mesh.ply", "mesh.glb", "mesh.json"} <= names  # nothing lost
        assert not any(n.startswith("asset") for n in names)


def test_a_running_asset_bake_stops_on_cancel(server: LiveServer, trained, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import time

    import core.asset.export as export_mod

    key, job_id = trained
    baking = []
    real = export_mod.bake_views

    def slow_bake(*a, **kw):  # type: ignore[no-untyped-def]
        baking.append(1)
        time.sleep(1.0)
        return real(*a, **kw)

    monkeypatch.setattr(export_mod, "bake_views", slow_bake)
    body = {"resolution": 32, "asset": {"faces": 1000, "texture_size": 64, "views": 2}}
    with server.client(key) as c:
        mesh_job = c.post(f"/v1/jobs/{job_id}/meshes", json=body).json()
        wait_for(lambda: baking, timeout=60)
        assert c.post(f"/v1/jobs/{mesh_job['id']}/cancel").status_code == 200
        done = _finished(c, mesh_job["id"])
        assert done["state"] == "cancelled", done
        names = {a["name"] for a in list_all(c, f"/v1/jobs/{mesh_job['id']}/artifacts")}
        assert "mesh.ply" in names and not any(n.startswith("asset") for n in names)


def test_another_owner_sees_nothing(server: LiveServer, trained) -> None:  # type: ignore[no-untyped-def]
    _, job_id = trained
    with server.client(server.new_key("intruder")) as c:
        assert c.post(f"/v1/jobs/{job_id}/meshes", json={}).status_code == 404
        assert c.get(f"/v1/jobs/{job_id}/meshes").status_code == 404


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"resolution": 100_000}, "body.resolution"),
        ({"resolution": 4}, "body.resolution"),
        ({"color": "chrome"}, "body.color"),
        ({"voxel": 1e-9}, "body.voxel"),
        ({"voxel": -1}, "body.voxel"),
        ({"keep_fraction": 2}, "body.keep_fraction"),
        ({"simplify": 1}, "body.simplify"),
        ({"grazing_blend": "sometimes"}, "body.grazing_blend"),
        ({"levels": 3}, "body.levels"),
        ({"asset": {"texture_size": 100}}, "body.asset.texture_size"),
        ({"asset": {"texture_size": 8192}}, "body.asset.texture_size"),
        ({"asset": {"faces": 999}}, "body.asset.faces"),
        ({"asset": {"faces": 2_000_001}}, "body.asset.faces"),
        ({"asset": {"views": 0}}, "body.asset.views"),
        ({"asset": {"views": 257}}, "body.asset.views"),
        ({"asset": {"occlusion": "maybe"}}, "body.asset.occlusion"),
        ({"asset": {"glossy": True}}, "body.asset.glossy"),
        ({"asset": 1}, "body.asset"),
    ],
)
def test_bad_mesh_requests_name_the_field(server: LiveServer, trained, body, field) -> None:  # type: ignore[no-untyped-def]
    key, job_id = trained
    with server.client(key) as c:
        before = c.get(f"/v1/jobs/{job_id}/meshes").json()["total"]
        r = c.post(f"/v1/jobs/{job_id}/meshes", json=body)
        assert r.status_code == 422, r.text
        assert r.headers["content-type"].startswith("application/problem+json")
        assert field in [e["field"] for e in r.json()["errors"]]
        assert c.get(f"/v1/jobs/{job_id}/meshes").json()["total"] == before  # nothing queued


def test_asset_texture_size_must_be_a_power_of_two(server: LiveServer, trained) -> None:  # type: ignore[no-untyped-def]
    """The 422 says what is expected, not only that the value is wrong."""
    key, job_id = trained
    with server.client(key) as c:
        r = c.post(f"/v1/jobs/{job_id}/meshes", json={"asset": {"texture_size": 1000}})
        assert r.status_code == 422, r.text
        (err,) = r.json()["errors"]
        assert err["field"] == "body.asset.texture_size"
        assert err["message"].startswith("texture_size must be a power of two: one of 64, "), err
        assert "4096; got 1000" in err["message"], err


def test_the_asset_field_is_documented(server: LiveServer) -> None:
    with server.client(None) as c:
        doc = c.get("/openapi.json").json()
    mesh = doc["components"]["schemas"]["MeshCreate"]["properties"]["asset"]
    assert "asset.glb" in mesh["description"]
    asset = doc["components"]["schemas"]["AssetCreate"]
    assert set(asset["properties"]) == {"faces", "texture_size", "views", "occlusion"}
    assert asset["properties"]["faces"]["minimum"] == 1000
    assert asset["properties"]["texture_size"]["maximum"] == 4096
    assert "power of two" in asset["properties"]["texture_size"]["description"]


def test_meshing_an_unfinished_job_is_a_conflict(server: LiveServer, scene) -> None:  # type: ignore[no-untyped-def]
    with server.client(server.new_key("early-owner")) as c:
        sid = _ready_scene(c, scene)
        server.queue.hold()
        try:
            job = c.post("/v1/jobs", json={"scene_id": sid, "config": TINY_CONFIG}).json()
            r = c.post(f"/v1/jobs/{job['id']}/meshes", json={})
            assert r.status_code == 409 and r.json()["type"].endswith("job-not-finished")
            assert c.post(f"/v1/jobs/{job['id']}/cancel").json()["state"] == "cancelled"
        finally:
            server.queue.release()


def test_cancelled_extraction_leaves_no_artifact(server: LiveServer, trained) -> None:  # type: ignore[no-untyped-def]
    key, job_id = trained
    with server.client(key) as c:
        server.queue.hold()
        try:
            mesh_job = c.post(f"/v1/jobs/{job_id}/meshes", json={"resolution": 48}).json()
            r = c.post(f"/v1/jobs/{mesh_job['id']}/cancel")
            assert r.json()["state"] == "cancelled"
        finally:
            server.queue.release()
        assert list_all(c, f"/v1/jobs/{mesh_job['id']}/artifacts") == []


def test_a_running_extraction_stops_on_cancel(server: LiveServer, trained, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Cancel while the extraction runs: the job ends cancelled, with no mesh files."""
    import core.meshing.mesh as mesh_mod

    key, job_id = trained
    started = []
    real = mesh_mod.model_depth_frame

    def slow_frame(*a, **kw):  # type: ignore[no-untyped-def]
        started.append(1)
        import time

        time.sleep(0.3)
        return real(*a, **kw)

    monkeypatch.setattr(mesh_mod, "model_depth_frame", slow_frame)
    with server.client(key) as c:
        mesh_job = c.post(f"/v1/jobs/{job_id}/meshes", json={"resolution": 48}).json()
        wait_for(lambda: started, timeout=60)
        assert c.post(f"/v1/jobs/{mesh_job['id']}/cancel").status_code == 200
        done = _finished(c, mesh_job["id"])
        assert done["state"] == "cancelled", done
        assert list_all(c, f"/v1/jobs/{mesh_job['id']}/artifacts") == []
    run = Path(server.settings.store_root) / "jobs" / mesh_job["id"] / "run"
    assert not list(run.glob("mesh*")) and not list(run.glob("*.tmp"))


def test_deleting_a_job_deletes_its_meshes(server: LiveServer, scene) -> None:  # type: ignore[no-untyped-def]
    with server.client(server.new_key("delete-owner")) as c:
        sid = _ready_scene(c, scene)
        cfg = {**TINY_CONFIG, "iterations": 6, "outputs": {"mesh": False}}
        job = _finished(c, c.post("/v1/jobs", json={"scene_id": sid, "config": cfg}).json()["id"])
        mesh = _finished(
            c, c.post(f"/v1/jobs/{job['id']}/meshes", json={"resolution": 32}).json()["id"]
        )
        assert mesh["state"] == "succeeded", mesh["error"]
        assert c.delete(f"/v1/jobs/{job['id']}").status_code == 204
        assert c.get(f"/v1/jobs/{mesh['id']}").status_code == 404
    store = Path(server.settings.store_root) / "jobs"
    assert not (store / mesh["id"]).exists() and not (store / job["id"]).exists()
