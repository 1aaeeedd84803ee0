"""Shared fixtures: where the optional dev data lives; one torch thread for tests."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

# longest test files first, for two xdist workers (tests/file_order.py)
from tests.file_order import (  # noqa: F401
    pytest_collection_modifyitems,
    pytest_runtest_logreport,
    pytest_sessionfinish,
)

# Tests run many small tensor ops: a second intra-op thread gains nothing there and,
# on a loaded 2-core machine, makes every op wait for a descheduled thread (measured
# 84 ms vs 1.35 s per training step). One thread keeps test time independent of load.
torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _one_thread_layout():
    """Undo a CLI test's ``configure_cpu_threads`` (main() applies it) after each test."""
    yield
    from core.kernels.pool import set_kernel_threads

    set_kernel_threads(None)
    torch.set_num_threads(1)


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
