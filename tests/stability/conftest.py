"""Shared fixtures of the stability suite.

Torch runs single-threaded here: the suite must finish in minutes on 2 shared cores,
and tiny tensors (24×24 images, a handful of Gaussians) gain nothing from threads
while oversubscribed cores make every op wait for both. The previous setting is
restored after each test, so running this folder with the rest changes nothing else.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch


@pytest.fixture(autouse=True)
def _single_thread() -> Iterator[None]:
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@pytest.fixture(scope="session")
def sphere_48():
    """Glossy sphere, 48 train views + 1 test view, 24×24: every view has a neighbour
    within 30°, so the multi-view loss runs (16 views would leave it planned off)."""
    from core.scene.synthetic import make_scene

    return make_scene("sphere", "glossy", n_train=48, n_test=1, size=24, seed=2, samples=2)
