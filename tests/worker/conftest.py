"""Fixtures for the worker suite: a tiny scene, committed through a live API."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.api.support import scene_files


@pytest.fixture(scope="session")
def scene(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, bytes]]:
    """A 24x24 glossy sphere, 6 train + 2 test views (the API suite's scene)."""
    from core.scene.synthetic import write_synthetic_scene

    root: Path = write_synthetic_scene(
        tmp_path_factory.mktemp("scene"), "sphere", "glossy", n_train=6, n_test=2, size=24
    )
    return scene_files(root)
