"""The compiled visibility record against the torch reference (record_visibility)."""

from __future__ import annotations

import pytest
import torch

from core.render.gaussians import Gaussians
from core.render.gbuffer import render_gbuffer
from core.render.orientation import (
    SEEN_COUNT,
    SEEN_DIR,
    add_orientation_state,
    record_visibility,
)
from core.scene.cameras import Camera, Intrinsics

from .test_silhouette import discs_on_the_sphere


def copy_model(g: Gaussians, dtype: torch.dtype) -> Gaussians:
    params = {k: v.detach().to(dtype).clone() for k, v in g.params.items()}
    return Gaussians(params, g.sh_degree)


@pytest.fixture(scope="module")
def sphere_view():
    """Discs on the sphere plus a few off it (in front, behind, outside the image),
    a view's rendered depth, and a valid mask with a hole punched in it."""
    g = discs_on_the_sphere(4000)
    extra = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -3.0], [40.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    with torch.no_grad():
        g.params["means"].data[: len(extra)] = extra
    cam = Camera.look_at([0.0, 0.3, 3.0], [0, 0, 0], [0, 1, 0], Intrinsics(70, 70, 32, 32, 64, 64))
    with torch.no_grad():
        gb, _ = render_gbuffer(g, cam, sh_degree=0, antialiased=True, lowpass=1 / 12)
    valid = gb.depth_valid.clone()
    valid[20:30, 20:30] = False
    return g, cam, gb.depth, valid


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_matches_the_torch_record(sphere_view, dtype):
    g0, cam, depth, valid = sphere_view
    out = {}
    for compiled in (False, True):
        g = copy_model(g0, dtype)
        add_orientation_state(g)
        g.params[SEEN_COUNT].data[::3] = 2.0  # sums that already hold earlier views
        g.params[SEEN_DIR].data[::3] = 0.5
        hits = [
            record_visibility(g, c, depth.to(dtype), valid, compiled=compiled) for c in (cam, cam)
        ]
        out[compiled] = (hits, g.params[SEEN_DIR].detach(), g.params[SEEN_COUNT].detach())
    (h_ref, s_ref, c_ref), (h_new, s_new, c_new) = out[False], out[True]
    assert 0 < h_ref[0] < g0.num  # the far side and the off-surface points are not on it
    if dtype == torch.float64:
        assert h_new == h_ref
        torch.testing.assert_close(c_new, c_ref, rtol=0, atol=0)
        torch.testing.assert_close(s_new, s_ref, rtol=1e-12, atol=1e-12)
    else:  # float32 against float64 arithmetic: a centre on the tolerance may flip
        assert abs(h_new[0] - h_ref[0]) <= 2
        same = c_new == c_ref
        assert int((~same).sum()) <= 4
        torch.testing.assert_close(s_new[same], s_ref[same], rtol=1e-5, atol=1e-6)


def test_points_off_the_surface_or_image_are_not_recorded(sphere_view):
    g0, cam, depth, valid = sphere_view
    g = copy_model(g0, torch.float32)
    add_orientation_state(g)
    record_visibility(g, cam, depth, valid, compiled=True)
    count = g.params[SEEN_COUNT].detach()
    # in front of the surface (on it, as far as the depth test goes) / behind / outside / centre
    assert count[0] == 1.0 and count[1] == 0.0 and count[2] == 0.0 and count[3] == 0.0
    # the recorded direction is the unit vector to the camera
    d = g.params[SEEN_DIR].detach()[0]
    expect = cam.center.float() - g.params["means"].detach()[0]
    torch.testing.assert_close(d, expect / expect.norm(), rtol=1e-6, atol=1e-6)
