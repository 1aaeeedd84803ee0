"""The Python client against a real server (uvicorn on loopback, embedded job runner):
scene folder → commit → job → follow → metrics → download, every byte checked."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest
from glint_client import Client, IntegrityError, JobCancelled, NotFound, ValidationError
from glint_client.models import Job

from tests.api.support import LiveServer
from tests.client.conftest import QUICK_CONFIG
from tests.client.support import CountingTransport, sha256


def test_folder_to_trained_job(server: LiveServer, scene_dir: Path, key: str) -> None:
    files = sorted(p for p in scene_dir.rglob("*") if p.is_file())
    with Client(server.url, key) as c:
        scene = c.create_scene_from(scene_dir)
        assert scene["state"] == "ready" and scene["format"] == "blender"
        assert scene["file_count"] == len(files)
        assert scene["report"] is not None and scene["report"]["views"] == 8
        held = {f["path"]: f["sha256"] for f in c.scene_files(scene["id"])}
        assert held == {p.relative_to(scene_dir).as_posix(): sha256(p) for p in files}

        job = c.create_job(scene["id"], QUICK_CONFIG, iterations=20)
        seen: list[Job] = []
        done = c.wait(job["id"], on_update=seen.append)
        assert done["state"] == "succeeded", done["error"]
        assert seen and seen[-1]["state"] == "succeeded"
        versions = [j["version"] for j in seen]
        assert versions == sorted(set(versions))  # each change once, in order
        assert [j["id"] for j in c.list_jobs("succeeded")] == [job["id"]]

        rows = c.metrics(job["id"])
        assert rows and rows[-1]["iteration"] == 20
        assert all(r["psnr"] is not None for r in rows)
        assert len(c.metrics(job["id"], points=2)) == 2


def test_download_verifies_resumes_and_skips(trained: tuple[str, str, Job], tmp_path: Path) -> None:
    url, key, job = trained
    counter = CountingTransport()
    with Client(url, key, transport=counter) as c:
        arts = {a["name"]: a for a in c.artifacts(job["id"])}
        assert {"checkpoint.pt", "point_cloud.ply", "report.md", "metrics.jsonl"} <= set(arts)
        paths = c.download(job["id"], tmp_path)
        assert {p.relative_to(tmp_path).as_posix() for p in paths} == set(arts)
        for p in paths:
            assert sha256(p) == arts[p.relative_to(tmp_path).as_posix()]["sha256"]
        assert not list(tmp_path.rglob("*.part"))
        whole = counter.downloaded()

        # a download cut off halfway: the .part is continued with a Range request
        ck = tmp_path / "checkpoint.pt"
        data = ck.read_bytes()
        ck.unlink()
        (tmp_path / "checkpoint.pt.part").write_bytes(data[: len(data) // 2])
        before = counter.downloaded()
        c.download(job["id"], tmp_path, ["checkpoint.pt"])
        assert ck.read_bytes() == data
        assert counter.downloaded() - before == len(data) - len(data) // 2

        # files present with the right checksum are not fetched again; a damaged one is
        report = tmp_path / "report.md"
        report.write_text("damaged")
        before = counter.downloaded()
        c.download(job["id"], tmp_path)
        assert counter.downloaded() - before == arts["report.md"]["size"]
        assert sha256(report) == arts["report.md"]["sha256"]
        assert whole >= sum(a["size"] for a in arts.values())

        # chosen artifacts by glob
        chosen = c.download(job["id"], tmp_path / "renders-only", ["renders/*"])
        assert chosen and all(p.parent.name == "renders" for p in chosen)


class Corrupting(httpx.HTTPTransport):
    """Flips a bit in the first ``times`` artifact bodies (a damaged store or proxy)."""

    def __init__(self, times: int) -> None:
        super().__init__()
        self.left = times

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        response = super().handle_request(request)
        if "/artifacts/" not in request.url.path or self.left <= 0:
            return response
        self.left -= 1
        data = response.read()
        bad = bytes([data[0] ^ 1]) + data[1:]
        return httpx.Response(response.status_code, headers=response.headers, content=bad)


def test_a_download_is_checked_against_its_sha256(
    trained: tuple[str, str, Job], tmp_path: Path
) -> None:
    url, key, job = trained
    with Client(url, key, transport=Corrupting(1)) as c:  # once: fetched again, whole
        (path,) = c.download(job["id"], tmp_path / "once", ["report.md"])
        assert sha256(path) == next(
            a["sha256"] for a in c.artifacts(job["id"]) if a["name"] == "report.md"
        )
    with Client(url, key, transport=Corrupting(2)) as c, pytest.raises(IntegrityError):
        c.download(job["id"], tmp_path / "twice", ["report.md"])
    assert list((tmp_path / "twice").iterdir()) == []  # neither the file nor a .part


def test_follow_reconnects_with_last_event_id(trained: tuple[str, str, Job]) -> None:
    """The event stream breaks off after the job's event: the follower opens it again
    with Last-Event-ID, so the version it saw is not sent twice, and gets the end."""
    url, key, job = trained

    def cut_first_stream(request: httpx.Request, n: int) -> int | None:
        return 2 if n == 1 else None  # "retry:", then the job event, then the cut

    counter = CountingTransport(cut=cut_first_stream)
    with Client(url, key, transport=counter) as c:
        follower = c.follow(job["id"])
        seen = list(follower)
    assert [j["version"] for j in seen] == [job["version"]]
    assert follower.end_state == "succeeded" and follower.reconnects == 1
    assert [h.get("last-event-id") for h in counter.headers] == [None, str(job["version"])]


def test_problem_json_arrives_as_typed_exception(
    glint: Client, scene_dir: Path, tmp_path: Path
) -> None:
    with pytest.raises(NotFound) as nf:
        glint.get_job("job_doesnotexist")
    assert nf.value.status == 404 and nf.value.slug == "not-found"

    scene = glint.create_scene("bad")
    with pytest.raises(ValidationError) as bad:
        glint.create_job(scene["id"], {"iterations": -5})
    assert bad.value.field == "body.config.iterations"
    assert bad.value.type == "urn:glint:problem:validation-error"

    # a scene whose pose is broken: commit names the file and the field
    frames = json.loads((scene_dir / "transforms_train.json").read_text())
    frames["frames"][0]["transform_matrix"] = "not a matrix"
    broken = tmp_path / "broken"
    (broken / "train").mkdir(parents=True)
    (broken / "transforms_train.json").write_text(json.dumps(frames))
    for p in (scene_dir / "train").glob("*"):
        (broken / "train" / p.name).write_bytes(p.read_bytes())
    with pytest.raises(ValidationError) as invalid:
        glint.create_scene_from(broken)
    e = invalid.value
    assert e.slug == "invalid-scene" and e.file == "transforms_train.json"
    assert e.field is not None and e.field.startswith("frames[0]")


def test_cancel_and_delete(glint: Client, scene_dir: Path) -> None:
    scene = glint.create_scene_from(scene_dir)
    job = glint.create_job(scene["id"], {**QUICK_CONFIG, "iterations": 5000})
    glint.cancel(job["id"])
    with pytest.raises(JobCancelled):
        glint.wait(job["id"])
    glint.delete_job(job["id"])
    with pytest.raises(NotFound):
        glint.get_job(job["id"])
