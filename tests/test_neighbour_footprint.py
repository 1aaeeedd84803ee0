"""A training step renders its neighbour view only where L_multi reads it: the loss and
every gradient are those of a whole neighbour view."""

from __future__ import annotations

import math

import pytest
import torch

from core.render.gaussians import Gaussians
from core.render.gbuffer import geometry_depth, render_gbuffer
from core.scene.cameras import Camera, Intrinsics
from core.training.losses import multi_view_footprint, multi_view_loss, multi_view_pixels


def _scene() -> tuple[Gaussians, Camera, Camera]:
    """Flat random splats in a ball and two views 10° apart about it."""
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(3000, 3, generator=g) * 0.45
    gs = Gaussians.from_points(pts, torch.rand(3000, 3, generator=g), sh_degree=0, radius=1.0)
    with torch.no_grad():
        gs.params["opacity_logits"].uniform_(-1.0, 2.0, generator=g)
        gs.params["log_scales"][:, 2] -= 3.0
    intr = Intrinsics.from_fov_x(0.69, 48, 40)
    cam = Camera.look_at([0.0, -3.0, 0.5], [0, 0, 0], [0, 0, 1], intr)
    a = math.radians(10.0)
    rot = torch.eye(4, dtype=torch.float64)
    rot[:2, :2] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    return gs, cam, Camera(cam.intrinsics, cam.world_to_cam @ rot, "neighbour")


@pytest.mark.parametrize("order", ["plane", "centre"])
def test_the_neighbour_at_its_footprint_gives_the_whole_views_loss_and_gradients(order):
    gs, cam, nb = _scene()
    with torch.no_grad():
        gb, _ = render_gbuffer(gs, cam, sh_degree=0, backend="cpu", geometry_only=True,
                               splat_order=order)  # fmt: skip
    depth, valid = geometry_depth(gb, True)
    pixels = multi_view_pixels(valid, 300, torch.Generator().manual_seed(1))
    footprint = multi_view_footprint(depth, pixels, cam, nb)
    assert footprint is not None and footprint.shape == (40, 48)
    assert 100 < int(footprint.sum()) < 0.8 * footprint.numel()
    out = {}
    for name, asked in (("whole", None), ("footprint", footprint)):
        for p in gs.params.values():
            p.grad = None
        gb_n, _ = render_gbuffer(gs, nb, sh_degree=0, backend="cpu", geometry_only=True,
                                 splat_order=order, pixels=asked)  # fmt: skip
        d_n, v_n = geometry_depth(gb_n, True)
        loss, stats = multi_view_loss(depth, valid, cam, d_n, v_n, nb, pixels=pixels)
        loss.backward()
        grads = {k: p.grad.clone() for k, p in gs.params.items() if p.grad is not None}
        out[name] = (loss.detach(), stats, grads, gb_n.alpha.detach())
    whole, part = out["whole"], out["footprint"]
    assert whole[1]["kept"] > 50  # the round trips hold: the test compares something
    assert torch.equal(part[0], whole[0]) and part[1] == whole[1]
    assert whole[2].keys() == part[2].keys() and "means" in whole[2]
    for k, g in whole[2].items():
        assert float(g.abs().max()) > 0, k
        assert torch.equal(part[2][k], g), k  # the same sums: only zeros were left out
    # what the neighbour left out it did leave empty
    assert float(part[3][~footprint].abs().max()) == 0.0
    assert float(whole[3][~footprint].max()) > 0.5


def test_the_draw_is_the_losss_own():
    """Drawing the pixels first consumes the generator as the loss's own draw did."""
    gs, cam, nb = _scene()
    with torch.no_grad():
        gb, _ = render_gbuffer(gs, cam, sh_degree=0, backend="cpu", geometry_only=True)
    depth, valid = geometry_depth(gb, True)
    drawn = multi_view_pixels(valid, 300, torch.Generator().manual_seed(4))
    a, _ = multi_view_loss(depth, valid, cam, depth, valid, nb, pixels=drawn)
    b, _ = multi_view_loss(depth, valid, cam, depth, valid, nb, n_pixels=300,
                           generator=torch.Generator().manual_seed(4))  # fmt: skip
    assert drawn.numel() == 300 and torch.equal(a, b)
