"""Fixtures: one real uvicorn per database backend, API keys, and a tiny glossy scene."""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.api.support import LiveServer, ThreadQueue, make_settings, scene_files

PG_URL = os.environ.get("GLINT_TEST_PG", "postgresql://postgres@127.0.0.1:5432/test")


@pytest.fixture(scope="session")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 24x24 glossy sphere, 6 train + 2 test views, Blender format."""
    from core.scene.synthetic import write_synthetic_scene

    return write_synthetic_scene(
        tmp_path_factory.mktemp("scene"), "sphere", "glossy", n_train=6, n_test=2, size=24
    )


@pytest.fixture(scope="session")
def scene(scene_dir: Path) -> list[tuple[str, bytes]]:
    return scene_files(scene_dir)


def _start(root: Path, database_url: str | None = None) -> LiveServer:
    settings = make_settings(root, database_url)
    return LiveServer(settings, ThreadQueue(settings)).start()


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """The API on SQLite (the default backend)."""
    srv = _start(tmp_path_factory.mktemp("sqlite-server"))
    yield srv
    srv.queue.join(60)
    srv.stop()


def _pg_database() -> Iterator[str]:
    try:
        import psycopg

        admin = psycopg.connect(PG_URL, autocommit=True, connect_timeout=3)
    except Exception as exc:  # no server, no driver, no access
        pytest.skip(f"PostgreSQL not reachable at {PG_URL}: {exc}")
    name = f"glint_api_test_{uuid.uuid4().hex[:12]}"
    admin.execute(f'CREATE DATABASE "{name}"')
    base = PG_URL.rsplit("/", 1)[0]
    try:
        yield f"{base.replace('postgresql://', 'postgresql+psycopg://', 1)}/{name}"
    finally:
        admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        admin.close()


@pytest.fixture(scope="session")
def pg_url() -> Iterator[str]:
    """A fresh, empty PostgreSQL database (dropped afterwards), or a skip."""
    yield from _pg_database()


@pytest.fixture(scope="session")
def pg_server(tmp_path_factory: pytest.TempPathFactory, pg_url: str) -> Iterator[LiveServer]:
    srv = _start(tmp_path_factory.mktemp("pg-server"), pg_url)
    yield srv
    srv.queue.join(60)
    srv.stop()
    srv.app.state.database.dispose()


@pytest.fixture(params=["sqlite", "postgresql"])
def any_server(request: pytest.FixtureRequest) -> LiveServer:
    """Each test using this runs once per database backend."""
    name = "server" if request.param == "sqlite" else "pg_server"
    return request.getfixturevalue(name)


@pytest.fixture
def key(server: LiveServer) -> str:
    """A fresh owner for each test, so tests never see each other's resources."""
    return server.new_key(f"owner-{uuid.uuid4().hex[:8]}")


@pytest.fixture
def client(server: LiveServer, key: str):  # type: ignore[no-untyped-def]
    with server.client(key) as c:
        yield c
