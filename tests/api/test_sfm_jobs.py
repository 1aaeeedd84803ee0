"""Photos without poses through the API (issue 23): upload, commit, a job whose ``sfm``
phase recovers the cameras and then trains; SfM failures that name the photos and keep
the upload; SfM options checked when the job is submitted.

Real uvicorn, real runner (the queue double runs ``run_job`` on threads, as the embedded
queue does), the directory store; the bucket and Celery path is in
``tests/worker/test_s3.py``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import typing
from pathlib import Path

import httpx
from sqlalchemy import update

from api.schemas import SfmConfig
from api.service.models import Job
from api.service.runner import run_job
from tests.api.archives import make_zip
from tests.api.support import TINY_CONFIG, LiveServer, job_events, list_all, multipart, wait_for
from tests.photo_capture import VIEWS, photo_files, stray_files

TERMINAL = {"succeeded", "failed", "cancelled"}
SFM_STEPS = {"start", "features", "matching", "mapping", "undistort"}
CONFIG = {**TINY_CONFIG, "iterations": 10, "eval": {"every": 10, "views": 1}}
SPARSE = {"sparse/0/cameras.bin", "sparse/0/images.bin", "sparse/0/points3D.bin"}


def _scene(c: httpx.Client, files: list[tuple[str, bytes]], *, archive: bool = False) -> dict:
    """A committed scene of ``files``; its body (the commit's answer)."""
    sid = c.post("/v1/scenes", json={"name": "photos"}).json()["id"]
    if archive:
        r = c.post(
            f"/v1/scenes/{sid}/archive",
            content=make_zip(files),
            headers={"Content-Type": "application/zip"},
        )
    else:
        r = c.post(f"/v1/scenes/{sid}/files", files=multipart(files))
    assert r.status_code == 201, r.text
    r = c.post(f"/v1/scenes/{sid}/commit")
    assert r.status_code == 200, r.text
    return dict(r.json())


def _hashes(c: httpx.Client, scene_id: str) -> dict[str, str]:
    return {f["path"]: f["sha256"] for f in list_all(c, f"/v1/scenes/{scene_id}/files")}


def _sha(files: list[tuple[str, bytes]]) -> dict[str, str]:
    return {p: hashlib.sha256(b).hexdigest() for p, b in files}


def _job(c: httpx.Client, job_id: str) -> dict:
    return dict(c.get(f"/v1/jobs/{job_id}").json())


def _finished(c: httpx.Client, job_id: str) -> dict:
    return dict(wait_for(lambda: (j := _job(c, job_id))["state"] in TERMINAL and j, 180, 0.2))


def test_photos_without_poses_train_through_an_sfm_phase(
    server: LiveServer, client: httpx.Client
) -> None:
    c = client
    files = photo_files()  # images/ and masks/
    scene = _scene(c, files)
    report = scene["report"]
    assert (scene["state"], scene["format"], report["needs_sfm"]) == ("ready", "images", True)
    assert (report["views"], report["masks"], report["resolution"]) == (VIEWS, True, [128, 96])
    assert report["intrinsics"] is None and report["center"] is None

    r = c.post(
        "/v1/jobs",
        json={"scene_id": scene["id"], "config": CONFIG, "sfm": {"matching": "exhaustive"}},
    )
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["sfm"] == {
        "options": {**SfmConfig().model_dump(), "matching": "exhaustive"},
        "result": None,
    }
    events = [d for k, d in job_events(c, job["id"]) if k == "job"]
    done = events[-1]
    assert done["state"] == "succeeded", done["error"]

    # the stream showed the sfm phase, its steps and their progress, then training
    phases = [e["phase"] for e in events if e["phase"]]
    sfm = [e for e in events if e["phase"] == "sfm"]
    assert sfm and phases.index("sfm") == 0 and phases[-1] != "sfm", phases
    assert all(e["stage"]["name"] == "sfm" for e in sfm)
    assert {e["stage"]["step"] for e in sfm} <= SFM_STEPS
    steps = [e["stage"] for e in sfm if "done" in e["stage"]]
    assert all(0 < s["done"] <= s["total"] for s in steps), steps
    result = done["sfm"]["result"]
    assert (result["images"], result["registered"], result["unregistered"]) == (VIEWS, VIEWS, [])
    assert result["cameras"] == 1 and result["points3D"] > 0

    # the report and the sparse model are artifacts, beside the run's own
    arts = {a["name"]: a for a in list_all(c, f"/v1/jobs/{job['id']}/artifacts")}
    assert {"sfm_report.json", "sfm_report.txt", "checkpoint.pt", "scene.json"} | SPARSE <= set(
        arts
    )
    saved = c.get(arts["sfm_report.json"]["url"]).json()
    assert saved["registered"] == VIEWS and saved["matching"]["strategy"] == "exhaustive"
    assert f"registered {VIEWS} of {VIEWS} images" in c.get(arts["sfm_report.txt"]["url"]).text
    for name in SPARSE:
        body = c.get(arts[name]["url"]).content
        assert hashlib.sha256(body).hexdigest() == arts[name]["sha256"]

    # the job's scene sits beside its run folder; the upload is as it was sent
    store = Path(server.settings.store_dir)
    job_dir = store / "jobs" / job["id"]
    assert sorted(p.name for p in job_dir.iterdir()) == ["run", "scene"]  # no SfM leftovers
    assert (job_dir / "run" / "scene.json").read_text().find("../scene") >= 0
    assert _hashes(c, scene["id"]) == _sha(files)
    assert c.get(f"/v1/scenes/{scene['id']}").json()["state"] == "ready"

    # delivered again (at least once): the recorded SfM scene is used, not made again
    report_file = job_dir / "scene" / "sfm_report.json"
    made = report_file.stat().st_mtime_ns
    with server.database.write() as s:
        s.execute(update(Job).where(Job.id == job["id"]).values(state="queued", lease=None))
    assert run_job(job["id"], server.settings) == "succeeded"
    assert report_file.stat().st_mtime_ns == made
    again = _job(c, job["id"])
    assert again["sfm"]["result"] == result and again["phase"] != "sfm", again
    assert {a["name"] for a in list_all(c, f"/v1/jobs/{job['id']}/artifacts")} >= SPARSE

    # a mesh of the trained job reads the SfM scene (its cameras and masks)
    r = c.post(f"/v1/jobs/{job['id']}/meshes", json={"resolution": 24})
    assert r.status_code == 201, r.text
    mesh = _finished(c, r.json()["id"])
    assert mesh["state"] == "succeeded", mesh["error"]


def test_sfm_failure_names_the_photos_and_keeps_the_upload(client: httpx.Client) -> None:
    c = client
    strays = stray_files(4)
    files = photo_files(folder="", masks=False) + strays  # photos at the top level, zipped
    scene = _scene(c, files, archive=True)
    assert scene["report"]["views"] == VIEWS + 4 and scene["report"]["masks"] is False

    r = c.post("/v1/jobs", json={"scene_id": scene["id"], "config": CONFIG})
    assert r.status_code == 201, r.text
    job = _finished(c, r.json()["id"])
    assert job["state"] == "failed"
    assert f"registered {VIEWS} of {VIEWS + 4} images" in job["error"], job["error"]
    assert all(name in job["error"] for name, _ in strays), job["error"]
    assert job["sfm"]["result"] is None

    # the failed run's report is an artifact; nothing was trained
    arts = {a["name"]: a for a in list_all(c, f"/v1/jobs/{job['id']}/artifacts")}
    assert set(arts) == {"sfm_report.json", "sfm_report.txt"}, set(arts)
    saved = c.get(arts["sfm_report.json"]["url"]).json()
    assert sorted(saved["unregistered"]) == sorted(n for n, _ in strays)

    # the upload is intact and the scene usable: a job that accepts fewer photos gets
    # through the sfm phase (cancelled once it trains, to keep the test short)
    assert _hashes(c, scene["id"]) == _sha(files)
    r = c.post(
        "/v1/jobs",
        json={
            "scene_id": scene["id"],
            "config": {**CONFIG, "iterations": 2000},
            "sfm": {"min_registered": 0.5},
        },
    )
    assert r.status_code == 201, r.text
    second = r.json()["id"]
    trained = wait_for(lambda: (j := _job(c, second))["iteration"] > 0 and j, 180, 0.1)
    assert trained["sfm"]["result"]["registered"] == VIEWS
    c.post(f"/v1/jobs/{second}/cancel")
    assert _finished(c, second)["state"] == "cancelled"


def test_cancel_stops_the_sfm_phase(server: LiveServer, client: httpx.Client) -> None:
    """A cancel during SfM ends the job within a poll or two, leaving no SfM scene."""
    c = client
    scene = _scene(c, stray_files(20))  # matching 190 pairs: a few seconds of SfM
    job_id = c.post("/v1/jobs", json={"scene_id": scene["id"], "config": CONFIG}).json()["id"]
    wait_for(lambda: _job(c, job_id)["phase"] == "sfm", 60, 0.02)
    assert c.post(f"/v1/jobs/{job_id}/cancel").status_code == 200
    job = _finished(c, job_id)
    assert (job["state"], job["error"], job["sfm"]["result"]) == ("cancelled", None, None), job
    job_dir = Path(server.settings.store_dir) / "jobs" / job_id
    left = [p.name for p in job_dir.iterdir()] if job_dir.is_dir() else []
    assert set(left) <= {"run"}, left  # no SfM scene, no half-made one


def test_sfm_options_are_checked_when_the_job_is_submitted(
    client: httpx.Client, scene: list[tuple[str, bytes]]
) -> None:
    c = client
    photos = _scene(c, stray_files(3))  # three photos, no masks: a valid upload
    posed = _scene(c, scene)
    cases = [
        (photos, {"matching": "fast"}, "body.sfm.matching"),
        (photos, {"mapper": "magic"}, "body.sfm.mapper"),
        (photos, {"min_registered": 1.5}, "body.sfm.min_registered"),
        (photos, {"seed": -1}, "body.sfm.seed"),
        (photos, {"speed": "max"}, "body.sfm.speed"),
        (photos, {"feature_masks": True}, "body.sfm.feature_masks"),  # the scene has none
        (posed, {}, "body.sfm"),  # poses given: nothing to recover
    ]
    for target, options, field in cases:
        r = c.post("/v1/jobs", json={"scene_id": target["id"], "sfm": options})
        assert r.status_code == 422, (options, r.text)
        problem = r.json()
        assert problem["type"] == "urn:glint:problem:validation-error"
        assert field in [e["field"] for e in problem["errors"]], (options, problem)
    assert c.get("/v1/jobs").json()["total"] == 0  # a refused request creates nothing


def test_photo_uploads_are_checked_at_commit(client: httpx.Client) -> None:
    c = client
    sid = c.post("/v1/scenes", json={"name": "two"}).json()["id"]
    assert c.post(f"/v1/scenes/{sid}/files", files=multipart(stray_files(2))).status_code == 201
    r = c.post(f"/v1/scenes/{sid}/commit")
    assert r.status_code == 422 and "at least 3 images" in r.json()["detail"], r.text

    files = photo_files(3)[:-1]  # the last photo's mask is missing
    sid = c.post("/v1/scenes", json={"name": "masks"}).json()["id"]
    assert c.post(f"/v1/scenes/{sid}/files", files=multipart(files)).status_code == 201
    r = c.post(f"/v1/scenes/{sid}/commit")
    assert r.status_code == 422, r.text
    assert "no mask for image view_002.png" in r.json()["detail"]
    assert r.json()["errors"][0]["file"] == "masks/view_002.png"

    sid = c.post("/v1/scenes", json={"name": "nothing"}).json()["id"]
    files = [("notes.txt", b"hello")]
    assert c.post(f"/v1/scenes/{sid}/files", files=multipart(files)).status_code == 201
    r = c.post(f"/v1/scenes/{sid}/commit")
    assert r.status_code == 422 and "plain photos without poses" in r.json()["detail"]


def test_sfm_config_mirrors_the_engine_options() -> None:
    """The API's SfM options are the engine's: same choices, same defaults."""
    from core.scene.sfm import SfmOptions
    from core.scene.sfm.mapping import MAPPERS
    from core.scene.sfm.matching import STRATEGIES

    fields = SfmConfig.model_fields
    assert typing.get_args(fields["matching"].annotation) == STRATEGIES
    assert typing.get_args(fields["mapper"].annotation) == MAPPERS
    engine = dataclasses.asdict(SfmOptions())
    assert {k: engine[k] for k in fields} == SfmConfig().model_dump()
