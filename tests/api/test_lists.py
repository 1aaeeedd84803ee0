"""Every list endpoint answers one page shape: items, total, limit, offset."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest

from api.service.models import Artifact, Job, Scene, SceneState, Worker, new_id
from tests.api.support import LiveServer, list_all, multipart

PAGE_KEYS = {"items", "total", "limit", "offset"}


def test_every_list_in_the_openapi_document_is_a_page(server: LiveServer) -> None:
    doc = server.app.openapi()
    schemas = doc["components"]["schemas"]
    lists = []
    for path, item in doc["paths"].items():
        for method, op in item.items():
            content = op.get("responses", {}).get("200", {}).get("content", {})
            schema = content.get("application/json", {}).get("schema", {})
            assert schema.get("type") != "array", f"{method.upper()} {path} answers a bare array"
            ref = schema.get("$ref", "").rsplit("/", 1)[-1]
            if ref.startswith("Page_"):
                lists.append(path)
                assert set(schemas[ref]["properties"]) == PAGE_KEYS, ref
                params = {p["name"] for p in op.get("parameters", [])}
                assert {"limit", "offset"} <= params, f"{path} takes no limit/offset"
    assert set(lists) == {
        "/v1/keys",
        "/v1/scenes",
        "/v1/scenes/{scene_id}/files",
        "/v1/scenes/{scene_id}/uploads",
        "/v1/jobs",
        "/v1/jobs/{job_id}/meshes",
        "/v1/jobs/{job_id}/webhooks",
        "/v1/jobs/{job_id}/artifacts",
        "/v1/workers",
    }


def _pages(c, path: str, n: int) -> None:  # type: ignore[no-untyped-def]
    """``n`` items, read two at a time, equal the items read in one page."""
    whole = c.get(path, params={"limit": 200}).json()
    assert set(whole) == PAGE_KEYS and whole["total"] == n == len(whole["items"])
    paged = []
    for offset in range(0, n, 2):
        page = c.get(path, params={"limit": 2, "offset": offset}).json()
        assert (page["total"], page["limit"], page["offset"]) == (n, 2, offset)
        paged += page["items"]
    assert paged == whole["items"]
    past = c.get(path, params={"offset": n + 5}).json()
    assert past["items"] == [] and past["total"] == n


def test_keys_files_artifacts_and_workers_are_paged(server: LiveServer) -> None:
    key = server.new_key("pager")
    with server.client(key) as c:
        for i in range(4):
            assert c.post("/v1/keys", json={"name": f"k{i}"}).status_code == 201
        _pages(c, "/v1/keys", 5)

        sid = c.post("/v1/scenes", json={"name": "paged"}).json()["id"]
        files = [(f"f{i}.txt", b"x") for i in range(5)]
        assert c.post(f"/v1/scenes/{sid}/files", files=multipart(files)).status_code == 201
        _pages(c, f"/v1/scenes/{sid}/files", 5)
        assert [f["path"] for f in list_all(c, f"/v1/scenes/{sid}/files")] == [n for n, _ in files]

        jid = new_id("job")
        now = datetime.now(UTC)
        with server.database.write() as s:
            scene = s.get(Scene, sid)
            scene.state = SceneState.READY
            s.add(Job(id=jid, owner="pager", scene_id=sid, config={}, total_iterations=1))
            s.flush()
            for i in range(3):
                s.add(Artifact(job_id=jid, name=f"a{i}.txt", size=1, sha256="0" * 64,
                               content_type="text/plain"))  # fmt: skip
            for i in range(3):
                s.add(Worker(id=f"pager-{i}@host", host="host", pid=i, device="cpu",
                             expires_at=now + timedelta(minutes=5)))  # fmt: skip
        _pages(c, f"/v1/jobs/{jid}/artifacts", 3)
        workers = [w for w in list_all(c, "/v1/workers") if w["id"].startswith("pager-")]
        assert [w["id"] for w in workers] == [f"pager-{i}@host" for i in range(3)]
        with server.database.write() as s:
            for i in range(3):
                s.delete(s.get(Worker, f"pager-{i}@host"))


@pytest.mark.parametrize(
    ("query", "field"),
    [
        ("limit=0", "query.limit"),
        ("limit=1001", "query.limit"),
        ("limit=ten", "query.limit"),
        ("offset=-1", "query.offset"),
        ("offset=99999999999999999999", "query.offset"),
        ("offset=1.5", "query.offset"),
    ],
)
@pytest.mark.parametrize("path", ["/v1/keys", "/v1/workers", "/v1/scenes/scn_x/files"])
def test_bad_page_parameters_name_the_field(
    server: LiveServer, key: str, path: str, query: str, field: str
) -> None:
    with server.client(key) as c:
        r = c.get(f"{path}?{query}")
    assert r.status_code == 422, r.text
    assert r.headers["content-type"] == "application/problem+json"
    assert field in [e["field"] for e in r.json()["errors"]]


def test_a_page_is_at_most_page_size_max(server: LiveServer, key: str) -> None:
    with server.client(key) as c:
        page = c.get("/v1/keys", params={"limit": 1000}).json()
    assert page["limit"] == server.settings.page_size_max
