"""The OpenAPI document is complete: every error declared, as problem+json, with auth."""

from __future__ import annotations

from pathlib import Path

import pytest

from api.main import create_app
from tests.api.support import make_settings


@pytest.fixture(scope="module")
def spec() -> dict:
    return create_app(make_settings(Path("/nonexistent"))).openapi()


def _operations(spec: dict):  # type: ignore[no-untyped-def]
    for path, item in spec["paths"].items():
        for method, op in item.items():
            yield method.upper(), path, op


def test_every_path_is_versioned_and_ids_unique(spec: dict) -> None:
    ops = list(_operations(spec))
    assert all(path.startswith("/v1/") for _, path, _ in ops)
    ids = [op["operationId"] for *_, op in ops]
    assert len(ids) == len(set(ids))


def test_errors_are_problem_json(spec: dict) -> None:
    for method, path, op in _operations(spec):
        errors = {c: r for c, r in op["responses"].items() if c[0] in "45"}
        assert errors, f"{method} {path} declares no errors"
        for code, resp in errors.items():
            content = resp["content"]
            assert list(content) == ["application/problem+json"], (method, path, code)
            assert content["application/problem+json"]["schema"]["$ref"].endswith("/Problem")
    assert "HTTPValidationError" not in spec["components"]["schemas"]


def test_auth_declared_everywhere_but_health(spec: dict) -> None:
    assert spec["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"
    for method, path, op in _operations(spec):
        if path == "/v1/health":
            assert "security" not in op
            continue
        assert op.get("security") == [{"HTTPBearer": []}], (method, path)
        assert "401" in op["responses"], (method, path)


def test_success_responses_have_models(spec: dict) -> None:
    for method, path, op in _operations(spec):
        ok = {c: r for c, r in op["responses"].items() if c.startswith("2")}
        assert ok, (method, path)
        for code, resp in ok.items():
            if code == "204":
                assert "content" not in resp
            else:
                assert resp.get("content"), (method, path, code)
    job = spec["components"]["schemas"]["JobOut"]["properties"]
    for field in ("state", "phase", "iteration", "progress", "metrics", "n_gaussians", "eta_s"):
        assert field in job


def test_every_guarded_operation_says_its_scope(spec: dict) -> None:
    scopes = {}
    for method, path, op in _operations(spec):
        if path == "/v1/health":
            continue
        scope = op["x-glint-scope"]
        scopes[(method, path)] = scope
        if method == "GET":
            assert scope == "read", (method, path)
        if scope != "read" or path == "/v1/keys/{key_id}":
            assert "403" in op["responses"], (method, path)
    assert scopes[("POST", "/v1/keys")] == "admin"
    assert scopes[("POST", "/v1/jobs")] == scopes[("DELETE", "/v1/scenes/{scene_id}")] == "write"
    assert scopes[("POST", "/v1/jobs/{job_id}/viewer-token")] == "read"
    assert scopes[("DELETE", "/v1/keys/{key_id}")] == "read"  # itself; others need admin
