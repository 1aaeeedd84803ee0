"""Fixtures for the worker suite: a tiny scene, committed through a live API; a Redis of
its own per test module (a real server process, started and stopped here)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.api.support import scene_files
from tests.worker.support import RedisServer


@pytest.fixture(scope="session")
def scene(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, bytes]]:
    """A 24x24 glossy sphere, 6 train + 2 test views (the API suite's scene)."""
    from core.scene.synthetic import write_synthetic_scene

    root: Path = write_synthetic_scene(
        tmp_path_factory.mktemp("scene"), "sphere", "glossy", n_train=6, n_test=2, size=24
    )
    return scene_files(root)


@pytest.fixture(scope="module")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RedisServer]:
    srv = RedisServer(tmp_path_factory.mktemp("redis")).start()
    yield srv
    srv.stop()
