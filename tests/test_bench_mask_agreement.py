"""bench.mask_agreement: rendered masks agree with each other, masks that slip do not."""

from __future__ import annotations

import torch

from bench.mask_agreement import unsupported_rim_share
from core.scene.synthetic import make_scene


def _sphere(n_train: int = 16):  # type: ignore[no-untyped-def]
    return make_scene("sphere", "diffuse", n_train=n_train, n_test=1, size=48, samples=4)


def test_rendered_masks_agree() -> None:
    m = unsupported_rim_share(_sphere())
    assert m["share"] == 0.0 and m["views"] == 16 and m["rays"] > 16 * 50


def test_masks_that_slip_disagree() -> None:
    """Every other mask moved 3 px sideways (a pose error or a segmentation slip): rays
    just inside those silhouettes, on the side they moved toward, leave the other views'
    masks before they reach the object."""
    scene = _sphere()
    for v in scene.train[::2]:
        assert v.mask is not None
        v.mask = torch.roll(v.mask, shifts=3, dims=1)
    m = unsupported_rim_share(scene)
    assert m["share"] > 0.2 and m["worst_view"] > m["share"]


def test_without_two_masks_there_is_nothing_to_compare() -> None:
    scene = _sphere(n_train=4)
    for v in scene.train[1:]:
        v.mask = None
    assert unsupported_rim_share(scene) == {"share": None, "views": 1, "rays": 0}
