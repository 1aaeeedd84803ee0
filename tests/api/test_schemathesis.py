"""Property-based fuzzing of every operation from the OpenAPI schema: no 5xx, ever.

A dedicated server whose queue only records ids (created jobs stay queued), seeded
with a ready scene and a job so that generated requests also reach real rows. Each
operation gets positive and negative examples from schemathesis (bounded, and
derandomised so a failure reproduces); responses must also match the schema.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from api.main import create_app
from tests.api.support import LiveServer, RecordingQueue, make_settings, multipart

MAX_EXAMPLES = 30
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
]
# archive bodies are raw bytes, like octet-stream
schemathesis.serializer.alias(
    ["application/zip", "application/x-tar", "application/gzip"], "application/octet-stream"
)
# every operation of the app, read from its schema (no server needed to collect)
OPERATIONS = [
    (method.upper(), path)
    for path, item in create_app(make_settings(Path("/nonexistent"))).openapi()["paths"].items()
    for method in item
]


@pytest.fixture(scope="module")
def fuzz_server(tmp_path_factory: pytest.TempPathFactory, scene) -> Iterator[LiveServer]:
    srv = LiveServer(make_settings(tmp_path_factory.mktemp("fuzz")), RecordingQueue()).start()
    key = srv.new_key("fuzzer")
    with srv.client(key) as c:
        sid = c.post("/v1/scenes", json={"name": "seed"}).json()["id"]
        c.post(f"/v1/scenes/{sid}/files", files=multipart(scene))
        assert c.post(f"/v1/scenes/{sid}/commit").status_code == 200
        assert c.post("/v1/jobs", json={"scene_id": sid}).status_code == 201
    srv.fuzz_key = key  # type: ignore[attr-defined]
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def api_schema(fuzz_server: LiveServer):  # type: ignore[no-untyped-def]
    return schemathesis.openapi.from_url(f"{fuzz_server.url}/openapi.json")


def test_every_operation_is_fuzzed(api_schema) -> None:  # type: ignore[no-untyped-def]
    assert len(OPERATIONS) >= 20
    live = {(op.ok().method.upper(), op.ok().path) for op in api_schema.get_all_operations()}
    assert live == set(OPERATIONS)


@pytest.mark.parametrize(("method", "path"), OPERATIONS, ids=[f"{m} {p}" for m, p in OPERATIONS])
def test_no_server_errors(method: str, path: str, api_schema, fuzz_server: LiveServer) -> None:  # type: ignore[no-untyped-def]
    operation = api_schema[path][method]
    cases = st.one_of(
        operation.as_strategy(GenerationMode.POSITIVE),
        operation.as_strategy(GenerationMode.NEGATIVE),
    )
    headers = {"Authorization": f"Bearer {fuzz_server.fuzz_key}"}  # type: ignore[attr-defined]

    @given(case=cases)
    @settings(
        max_examples=MAX_EXAMPLES,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    def fuzz(case) -> None:  # type: ignore[no-untyped-def]
        case.call_and_validate(base_url=fuzz_server.url, headers=headers, checks=CHECKS, timeout=30)

    fuzz()
