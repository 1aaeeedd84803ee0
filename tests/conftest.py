"""Shared fixtures: where the optional dev data lives."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# ../shared/data beside the repository, or GLINT_SHARED_DATA
SHARED_DATA = Path(
    os.environ.get("GLINT_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)


@pytest.fixture
def shared_scene():
    """``shared_scene(name)`` -> path of a dev scene, or skip the test when it is absent."""

    def get(name: str) -> Path:
        path = SHARED_DATA / name
        if not path.is_dir():
            pytest.skip(f"dev scene {name} not found under {SHARED_DATA}")
        return path

    return get
