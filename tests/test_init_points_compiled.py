"""The compiled visual-hull test (core.training.init_points_compiled) against the torch
reference, and the points it finds."""

from __future__ import annotations

import pytest
import torch

from core.scene.synthetic import make_scene
from core.scene.views import Scene
from core.training.init_points import inside_hull, visual_hull_points


@pytest.fixture(scope="module")
def scene() -> Scene:
    s = make_scene("sphere", "glossy", n_train=12, n_test=1, size=24, samples=1)
    # a mask of another size (the lookup's offsets) and a view without one
    s.train[5].mask = torch.nn.functional.interpolate(
        s.train[5].mask[None, None], size=(17, 31), mode="bilinear"
    )[0, 0]
    s.train[7].mask = None
    return s


def _points(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    pts = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 8.0  # cameras at 3
    pts[:50] = 0.0  # the centre: inside every mask
    pts[50] = torch.tensor([float("nan"), 0.0, 0.0], dtype=torch.float64)
    return pts


@pytest.mark.parametrize("min_fraction", [0.0, 0.5, 0.9, 1.0])
def test_compiled_hull_test_matches_the_reference(scene, min_fraction) -> None:
    pts = _points(20_000, 1)
    ref = inside_hull(pts, scene, min_fraction, compiled=False)
    fast = inside_hull(pts, scene, min_fraction, compiled=True)
    assert 0.01 < float(ref.float().mean()) < 0.9  # both answers occur
    assert bool(ref[:50].all()) and not bool(ref[50])
    # float64 projections summed in another order may round a point's float32 pixel
    # position differently right at a mask edge; nothing else may differ
    assert int((ref != fast).sum()) <= 2


def test_hull_points_are_the_same_either_way(monkeypatch) -> None:
    import core.training.init_points as ip

    scene = make_scene("sphere", "glossy", n_train=12, n_test=1, size=24, samples=1)
    fast = visual_hull_points(scene, 400)
    real = ip.inside_hull
    monkeypatch.setattr(ip, "inside_hull", lambda *a, **k: real(*a, **k, compiled=False))
    ref = visual_hull_points(scene, 400)
    assert fast is not None and ref is not None
    assert fast[0].shape == ref[0].shape
    assert torch.allclose(fast[0], ref[0], atol=1e-6)


def test_compiled_refuses_what_it_does_not_cover(scene) -> None:
    with pytest.raises(ValueError, match="float64"):
        inside_hull(torch.zeros(3, 3, dtype=torch.float32), scene, 0.9, compiled=True)
