"""The whole service path on a tiny scene, over real HTTP, on SQLite and PostgreSQL."""

from __future__ import annotations

import hashlib

import httpx

from tests.api.support import (
    TINY_CONFIG,
    LiveServer,
    job_events,
    list_all,
    multipart,
    store_files,
    wait_for,
)

TERMINAL = {"succeeded", "failed", "cancelled"}


def test_create_upload_commit_train_download(any_server: LiveServer, scene) -> None:
    srv = any_server
    key = srv.new_key("flow-owner")
    with srv.client(key) as c:
        assert c.get("/v1/health").json()["status"] == "ok"
        r = c.post("/v1/scenes", json={"name": "glossy sphere"})
        assert r.status_code == 201, r.text
        scene_id = r.json()["id"]
        assert r.json()["state"] == "open"

        # upload in two parts
        half = len(scene) // 2
        for part in (scene[:half], scene[half:]):
            r = c.post(f"/v1/scenes/{scene_id}/files", files=multipart(part))
            assert r.status_code == 201, r.text
            got = {f["path"]: f for f in r.json()["files"]}
            for name, data in part:
                assert got[name]["size"] == len(data)
                assert got[name]["sha256"] == hashlib.sha256(data).hexdigest()
        listed = list_all(c, f"/v1/scenes/{scene_id}/files")
        assert [f["path"] for f in listed] == [n for n, _ in scene]

        # commit = validate
        r = c.post(f"/v1/scenes/{scene_id}/commit")
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["state"] == "ready"
        report = body["report"]
        assert report["format"] == "blender"
        assert (report["train_views"], report["test_views"], report["views"]) == (6, 2, 8)
        assert report["resolution"] == [24, 24]
        assert report["masks"] is True
        assert report["intrinsics"]["cx"] == 12.0

        # train
        r = c.post("/v1/jobs", json={"scene_id": scene_id, "config": TINY_CONFIG})
        assert r.status_code == 201, r.text
        job = r.json()
        assert job["state"] in ("queued", "running")
        assert job["total_iterations"] == 20
        job_id = job["id"]
        seen_running = []

        def finished() -> dict | None:
            j = c.get(f"/v1/jobs/{job_id}").json()
            if j["state"] == "running" and j["iteration"] > 0:
                seen_running.append(j)
            return j if j["state"] in TERMINAL else None

        job = wait_for(finished, timeout=150, every=0.2)
        assert job["state"] == "succeeded", job["error"]
        assert job["iteration"] == 20 and job["progress"] == 1.0
        assert job["n_gaussians"] and job["n_gaussians"] > 0
        assert job["metrics"]["psnr"] > 0
        assert job["eta_s"] == 0.0 and job["elapsed_s"] > 0
        assert job["plan"] is not None and job["error"] is None
        for j in seen_running:  # progress seen mid-run is consistent
            assert 0 < j["progress"] <= 1 and j["phase"]

        # the event stream of a finished job: its last state, then the end marker
        events = job_events(c, job_id)
        assert events[0][0] == "job" and events[0][1]["state"] == "succeeded"
        assert events[-1] == ("end", {"state": "succeeded"})

        # artifacts
        arts = {a["name"]: a for a in list_all(c, f"/v1/jobs/{job_id}/artifacts")}
        for name in (
            "checkpoint.pt",
            "point_cloud.ply",
            "envmap_cross.exr",
            "envmap_latlong.exr",
            "envmap_latlong.png",
            "report.md",
            "error_vs_time.png",
            "metrics.jsonl",
            "plan.json",
            "config.json",
            "outputs.json",
        ):
            assert name in arts, f"missing artifact {name}"
        assert any(n.startswith("renders/") and n.endswith(".png") for n in arts)
        assert arts["envmap_latlong.png"]["content_type"] == "image/png"

        ply = arts["point_cloud.ply"]
        full = c.get(ply["url"])
        assert full.status_code == 200
        assert hashlib.sha256(full.content).hexdigest() == ply["sha256"]
        assert full.content.startswith(b"ply")
        etag = full.headers["etag"]
        assert etag == f'"{ply["sha256"]}"'
        assert c.get(ply["url"], headers={"If-None-Match": etag}).status_code == 304
        part = c.get(ply["url"], headers={"Range": "bytes=10-99"})
        assert part.status_code == 206
        assert part.headers["content-range"] == f"bytes 10-99/{ply['size']}"
        assert part.content == full.content[10:100]
        tail = c.get(ply["url"], headers={"Range": "bytes=-16"})
        assert tail.status_code == 206 and tail.content == full.content[-16:]
        same = c.get(ply["url"], headers={"Range": "bytes=0-3", "If-Range": etag})
        assert same.status_code == 206 and same.content == b"ply\n"
        stale = c.get(ply["url"], headers={"Range": "bytes=0-3", "If-Range": '"older"'})
        assert stale.status_code == 200 and stale.content == full.content
        bad = c.get(ply["url"], headers={"Range": f"bytes={ply['size']}-"})
        assert bad.status_code == 416
        assert bad.headers["content-range"] == f"bytes */{ply['size']}"

        # no artifact tells where the server keeps its files
        assert_no_server_paths(c, srv, list(arts.values()))

    # the run folder and the scene live where workers expect them
    files = store_files(srv.settings.store_root)
    assert f"jobs/{job_id}/run/checkpoint.pt" in files
    assert f"scenes/{scene_id}/files/transforms_train.json" in files
    assert not [f for f in files if f.startswith("tmp/")]


def assert_no_server_paths(c: httpx.Client, srv: LiveServer, arts: list[dict]) -> None:
    """Download every artifact; none holds the store's or the data folder's path."""
    roots = {str(srv.settings.store_root), str(srv.settings.data_dir)}
    roots |= {str(srv.settings.store_root.resolve()), str(srv.settings.data_dir.resolve())}
    assert "scene.json" in {a["name"] for a in arts}  # the record that used to leak it
    for a in arts:
        r = c.get(a["url"])
        assert r.status_code == 200, (a["name"], r.status_code)
        for root in roots:  # text artifacts, and binary ones too (a pickled path is text)
            assert root.encode() not in r.content, f"{a['name']} holds the server path {root}"
