"""Numbers the engine cannot hold, anywhere in a JSON body, answer 422 naming the field."""

from __future__ import annotations

import json

import httpx
import pytest
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute

from api.main import ROUTERS
from api.strict_json import StrictJsonRoute, loads
from tests.api.support import LiveServer, multipart


def test_loads_keeps_ordinary_json() -> None:
    body = b'{"a": [1, -2, 3.5, 9223372036854775807, -9223372036854775808], "b": {"c": null}}'
    assert loads(body) == json.loads(body)


@pytest.mark.parametrize(
    ("body", "loc"),
    [
        ('{"config": {"iterations": 9223372036854775808}}', ("body", "config", "iterations")),
        ('{"x": -9223372036854775809}', ("body", "x")),
        ('{"x": [0, 1' + "0" * 5000 + "]}", ("body", "x", 1)),  # past Python's digit limit
        ('{"loss": {"scale": Infinity}}', ("body", "loss", "scale")),
        ('{"x": -Infinity}', ("body", "x")),
        ('{"x": NaN}', ("body", "x")),
        ('{"x": 1e400}', ("body", "x")),
        ("1e400", ("body",)),
    ],
)
def test_loads_refuses_numbers_naming_them(body: str, loc: tuple) -> None:
    with pytest.raises(RequestValidationError) as err:
        loads(body)
    assert [e["loc"] for e in err.value.errors()] == [loc]


def test_loads_deep_nesting_and_binary_are_syntax_errors() -> None:
    with pytest.raises(json.JSONDecodeError):
        loads("[" * 200_000 + "]" * 200_000)
    with pytest.raises(json.JSONDecodeError):
        loads(b"\x83\xff{}")


def test_every_api_route_parses_strictly() -> None:
    routes = [r for router in ROUTERS for r in router.routes if isinstance(r, APIRoute)]
    assert len(routes) > 20
    loose = [r.path for r in routes if not isinstance(r, StrictJsonRoute)]
    assert not loose, f"routes not built with StrictJsonRoute: {loose}"


@pytest.fixture(scope="module")
def ready_scene(server: LiveServer, scene) -> tuple[str, str]:
    key = server.new_key("strict-json")
    with server.client(key) as c:
        sid = c.post("/v1/scenes", json={"name": "strict"}).json()["id"]
        assert c.post(f"/v1/scenes/{sid}/files", files=multipart(scene)).status_code == 201
        assert c.post(f"/v1/scenes/{sid}/commit").status_code == 200
    return key, sid


def _post(server: LiveServer, key: str, path: str, text: str) -> httpx.Response:
    with server.client(key) as c:
        return c.post(path, content=text, headers={"Content-Type": "application/json"})


@pytest.mark.parametrize(
    ("config", "field"),
    [
        ('{"iterations": 9223372036854775808}', "body.config.iterations"),
        ('{"iterations": 18446744073709551616}', "body.config.iterations"),
        ('{"iterations": 1' + "0" * 5000 + "}", "body.config.iterations"),
        ('{"iterations": 10000001}', "body.config.iterations"),
        ('{"init_points": 1000000000000}', "body.config.init_points"),
        ('{"densify": {"max_gaussians": 1000000000000}}', "body.config.densify.max_gaussians"),
        ('{"envmap_resolution": 1000000}', "body.config.envmap_resolution"),
        ('{"loss": {"scale": Infinity}}', "body.config.loss.scale"),
        ('{"loss": {"scale": NaN}}', "body.config.loss.scale"),
        ('{"lr": {"means_init": 1e400}}', "body.config.lr.means_init"),
        ('{"plan_overrides": {"x": 99999999999999999999}}', "body.config.plan_overrides.x"),
    ],
)
def test_job_config_numbers(
    server: LiveServer, ready_scene: tuple[str, str], config: str, field: str
) -> None:
    key, sid = ready_scene
    with server.client(key) as c:
        before = c.get("/v1/jobs").json()["total"]
    r = _post(server, key, "/v1/jobs", f'{{"scene_id": "{sid}", "config": {config}}}')
    assert r.status_code == 422, r.text
    assert r.headers["content-type"] == "application/problem+json"
    body = r.json()
    assert body["type"] == "urn:glint:problem:validation-error"
    assert field in [e["field"] for e in body["errors"]], body
    with server.client(key) as c:
        assert c.get("/v1/jobs").json()["total"] == before  # nothing was created


def test_huge_numbers_in_other_bodies(server: LiveServer) -> None:
    key = server.new_key("strict-json-2")
    r = _post(server, key, "/v1/scenes", '{"name": 1' + "0" * 30 + "}")
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "body.name"
    r = _post(server, key, "/v1/jobs/job_x/meshes", '{"resolution": 99999999999999999999999}')
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "body.resolution"
    r = _post(server, key, "/v1/keys", "[" * 100_000 + "]" * 100_000)
    assert r.status_code == 400 and r.json()["type"] == "urn:glint:problem:malformed-json"
    with server.client(key) as c:
        r = c.post("/v1/keys", content=b"\x83\xff", headers={"Content-Type": "application/json"})
    assert r.status_code == 400 and r.json()["type"] == "urn:glint:problem:malformed-json"
