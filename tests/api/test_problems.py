"""Every error is problem+json with a stable, documented ``type``; 405 lists every method."""

from __future__ import annotations

import re
from pathlib import Path

import httpx
import pytest

from api.problems import STATUS_SLUGS
from tests.api.support import LiveServer

REPO = Path(__file__).resolve().parents[2]
DOC = REPO / "docs" / "api.md"


@pytest.mark.parametrize(
    ("method", "path", "allow"),
    [
        ("PUT", "/v1/scenes", "GET, POST"),
        ("PATCH", "/v1/jobs", "GET, POST"),
        ("PUT", "/v1/jobs/job_x", "GET, DELETE"),
        ("POST", "/v1/scenes/scn_x", "GET, DELETE"),
        ("PUT", "/v1/scenes/scn_x/files", "GET, POST"),
        ("GET", "/v1/jobs/job_x/cancel", "POST"),
        ("PUT", "/v1/jobs/job_x/meshes", "GET, POST"),
        ("PUT", "/v1/keys", "GET, POST"),
        ("PATCH", "/v1/keys/key_x", "DELETE"),
        ("POST", "/v1/health", "GET"),
        ("POST", "/openapi.json", "GET, HEAD"),
        ("POST", "/viewer/static/viewer.js", "GET, HEAD"),
    ],
)
def test_405_allow_lists_every_method_of_the_path(
    server: LiveServer, key: str, method: str, path: str, allow: str
) -> None:
    with server.client(key) as c:
        r = c.request(method, path)
    assert r.status_code == 405, r.text
    assert r.headers["allow"] == allow
    assert r.headers["content-type"] == "application/problem+json"
    body = r.json()
    assert body["type"] == "urn:glint:problem:method-not-allowed"
    assert body["status"] == 405 and allow in body["detail"]


def _errors(server: LiveServer, key: str) -> dict[str, httpx.Response]:
    with server.client(key) as c, server.client(None) as anon:
        return {
            "unknown route": c.get("/v1/teapots"),
            "unknown top-level route": c.get("/nothing/here"),
            "unknown static file": c.get("/viewer/static/nope.js"),
            "wrong method": c.put("/v1/scenes"),
            "validation": c.get("/v1/jobs?limit=0"),
            "body validation": c.post("/v1/scenes", json={"name": 5}),
            "malformed JSON": c.post(
                "/v1/scenes", content=b"{", headers={"Content-Type": "application/json"}
            ),
            "unsupported media type": c.post("/v1/scenes", content=b"x"),
            "too large": c.post(
                "/v1/scenes/scn_x/archive",
                content=bytes(3 << 20),
                headers={"Content-Type": "application/zip"},
            ),
            "no key": anon.get("/v1/scenes"),
            "unknown id": c.get("/v1/jobs/job_nope"),
            "viewer without a token": c.get("/v1/jobs/job_x/viewer/envmap.png"),
        }


def test_every_error_is_problem_json_with_a_documented_type(server: LiveServer, key: str) -> None:
    doc = DOC.read_text()
    for name, r in _errors(server, key).items():
        assert r.status_code >= 400, (name, r.status_code)
        assert r.headers["content-type"] == "application/problem+json", (name, r.text)
        body = r.json()
        assert body["status"] == r.status_code, name
        assert body["title"] and body["detail"], name
        slug = body["type"].removeprefix("urn:glint:problem:")
        assert body["type"].startswith("urn:glint:problem:") and slug, name
        assert f"`{slug}`" in doc, f"{name}: type {slug!r} is not in docs/api.md"


def test_every_type_the_code_raises_is_documented() -> None:
    """A client switches on ``type``: each one the API can answer is in docs/api.md."""
    raised: dict[str, str] = {}
    for p in sorted((REPO / "api").rglob("*.py")):
        for m in re.finditer(r'\b[45]\d\d,\s*"([a-z][a-z0-9-]+)"', p.read_text()):
            raised.setdefault(m.group(1), str(p.relative_to(REPO)))
    raised.update(dict.fromkeys(STATUS_SLUGS.values(), "api/problems.py"))
    assert {"not-found", "unsafe-archive", "too-large", "malformed-json"} <= set(raised)
    doc = DOC.read_text()
    missing = {slug: where for slug, where in raised.items() if f"`{slug}`" not in doc}
    assert not missing, f"problem types missing from docs/api.md: {missing}"
