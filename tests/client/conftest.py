"""Fixtures for the client suite: a real ``glint serve`` app on a loopback port (the
embedded queue's job runner on threads), a fresh owner per test, a tiny scene folder,
and one trained job that the read-only tests share."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from glint_client import Client
from glint_client.models import Job

from tests.api.support import TINY_CONFIG, LiveServer, ThreadQueue, make_settings

# no mesh phase where a test does not look at meshes: it is most of a tiny job's time
QUICK_CONFIG = {**TINY_CONFIG, "outputs": {"mesh": False}}


@pytest.fixture(scope="session")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 24x24 glossy sphere, 6 train + 2 test views, Blender format (the API suite's)."""
    from core.scene.synthetic import write_synthetic_scene

    return write_synthetic_scene(
        tmp_path_factory.mktemp("scene"), "sphere", "glossy", n_train=6, n_test=2, size=24
    )


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    # loopback webhooks allowed: a test receives one on a local port
    settings = make_settings(tmp_path_factory.mktemp("client-server"), webhook_allow_private=True)
    srv = LiveServer(settings, ThreadQueue(settings)).start()
    yield srv
    srv.queue.join(60)
    srv.stop()


@pytest.fixture
def key(server: LiveServer) -> str:
    """A fresh owner for each test: lists and counts see only the test's own objects."""
    return server.new_key(f"client-{uuid.uuid4().hex[:8]}")


@pytest.fixture
def glint(server: LiveServer, key: str) -> Iterator[Client]:
    with Client(server.url, key, retries=1) as c:
        yield c


@pytest.fixture(scope="session")
def trained(server: LiveServer, scene_dir: Path) -> tuple[str, str, Job]:
    """(url, key, job): the scene folder uploaded, committed and trained to the end."""
    key = server.new_key("client-trained")
    with Client(server.url, key) as c:
        scene = c.create_scene_from(scene_dir)
        job = c.wait(c.create_job(scene["id"], QUICK_CONFIG)["id"])
    return server.url, key, job
