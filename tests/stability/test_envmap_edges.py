"""Environment-map lookups at the cube's singular places and with degenerate inputs.

Expected answers:

* a direction exactly on one of the 12 edges or 8 corners returns a finite value that
  is the limit from every adjacent face (|E(d + δ) − E(d)| ≤ 2·R·|δ|·max|texel|), for
  any direction length from 1e-15 to 1e30, with finite gradients w.r.t. texels and
  direction;
* zero-length (or below √tiny), NaN and ±Inf directions return exactly 0 and pass
  exactly 0 gradient to the texels, without disturbing valid directions in the batch;
* a zero normal reflects the view ray unchanged (r − 2(r·0)0 = r), so a covered pixel
  with a cancelled normal shows w_r·E(view ray); everything stays finite.
"""

from __future__ import annotations

import itertools

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from core.render.envmap import sample_cube
from core.render.gbuffer import GBuffer
from core.render.shading import deferred_shade, reflect, world_normals
from core.scene.cameras import Camera
from tests.stability.common import all_finite, camera

# 12 edge midpoints and 8 corners of the cube, as exact ±1/0 vectors.
EDGES = [v for v in itertools.product((-1.0, 0.0, 1.0), repeat=3) if sum(abs(c) for c in v) == 2.0]
CORNERS = list(itertools.product((-1.0, 1.0), repeat=3))
# Points on edges away from the midpoint (|third| < 1): still exactly on the edge.
EDGE_POINTS = [tuple(c if c != 0.0 else 0.37 for c in v) for v in EDGES]


def _texels(seed: int, r: int, dtype) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(6, r, r, 3, generator=g, dtype=torch.float64).to(dtype)


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    r=st.sampled_from([1, 2, 3, 8]),
    length=st.sampled_from([1e-15, 1e-3, 1.0, 1e10, 1e30]),
    dtype=st.sampled_from([torch.float32, torch.float64]),
)
def test_edges_and_corners_are_continuous_and_finite(seed, r, length, dtype):
    """Every edge point and corner: the value equals the limit from each nearby face."""
    tex = _texels(seed, r, dtype).requires_grad_(True)
    base = torch.tensor(EDGES + EDGE_POINTS + CORNERS, dtype=dtype)
    d = (base * length).requires_grad_(True)
    out = sample_cube(tex, d)
    assert all_finite(out)
    out.sum().backward()
    assert all_finite(tex.grad, d.grad), "gradients at edges/corners must be finite"
    eps = 1e-9 if dtype == torch.float64 else 1e-5
    tol = 2.0 * r * eps * 3.0 * float(tex.detach().max()) + (
        1e-12 if dtype == torch.float64 else 1e-6
    )
    with torch.no_grad():
        ref = sample_cube(tex, base)
        for axis in range(3):
            for sign in (-1.0, 1.0):
                nudge = torch.zeros(3, dtype=dtype)
                nudge[axis] = sign * eps
                near = sample_cube(tex, base + nudge)
                gap = float((near - ref).abs().max())
                assert gap <= tol, f"jump {gap:.2e} > {tol:.2e} nudging axis {axis} by {sign}·eps"
        scaled = sample_cube(tex, base * length)
        torch.testing.assert_close(
            scaled, ref, rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-12
        )


@settings(max_examples=30, deadline=None)
@given(
    bad=st.lists(
        st.sampled_from(
            [
                (0.0, 0.0, 0.0),
                (-0.0, 0.0, -0.0),
                ("tiny", "tiny", "tiny"),
                (float("nan"), 0.0, 1.0),
                (float("inf"), 0.0, 0.0),
                (1.0, float("-inf"), 1.0),
                (float("nan"), float("nan"), float("nan")),
            ]
        ),
        min_size=1,
        max_size=5,
    ),
    dtype=st.sampled_from([torch.float32, torch.float64]),
)
def test_degenerate_directions_return_zero_and_pass_no_gradient(bad, dtype):
    """Zero, sub-√tiny, NaN and ±Inf directions → exactly 0, zero texel gradient, and the
    valid directions of the same batch get the same values and gradients as alone."""
    tex = _texels(1, 4, dtype).requires_grad_(True)
    good = torch.tensor([[0.3, -0.8, 0.5], [1.0, 1.0, 1.0]], dtype=dtype)
    tiny = 0.5 * torch.finfo(dtype).tiny ** 0.5  # below the lookup's √tiny threshold
    bad_t = torch.tensor([[tiny if c == "tiny" else c for c in v] for v in bad], dtype=dtype)
    dirs = torch.cat([good, bad_t]).requires_grad_(True)
    out = sample_cube(tex, dirs)
    assert all_finite(out)
    assert float(out[2:].detach().abs().max()) == 0.0, "degenerate directions must return 0"
    out.sum().backward()
    assert all_finite(tex.grad, dirs.grad)
    assert float(dirs.grad[2:].abs().max()) == 0.0
    tex2 = tex.detach().clone().requires_grad_(True)
    alone = sample_cube(tex2, good)
    alone.sum().backward()
    torch.testing.assert_close(out[:2], alone, rtol=0, atol=0)
    torch.testing.assert_close(tex.grad, tex2.grad, rtol=0, atol=0)


def _gbuffer(cam: Camera, normal: torch.Tensor, alpha: float = 1.0, w_r: float = 0.5) -> GBuffer:
    h, w = cam.height, cam.width
    z = torch.zeros(h, w)
    return GBuffer(
        base=torch.full((h, w, 3), 0.1),
        normal=normal,
        plane_dist=z,
        w_r=torch.full((h, w), w_r),
        alpha=torch.full((h, w), alpha),
        camera=cam,
    )


def test_zero_normals_reflect_the_view_ray():
    """A covered pixel whose blended normal cancelled to 0 (or 1e-30): the reflection is
    the view ray itself, the specular term w_r·E(view ray), values and gradients finite."""
    cam = camera(8)
    _, view = cam.world_rays()
    tex = _texels(2, 4, torch.float32)

    class Env:
        def sample(self, d: torch.Tensor) -> torch.Tensor:
            return sample_cube(tex, d)

    for scale in (0.0, 1e-30):
        normal = (torch.ones(8, 8, 3) * scale).requires_grad_(True)
        gb = _gbuffer(cam, normal)
        assert float(world_normals(gb).detach().norm(dim=-1).max()) <= 1.0
        res = deferred_shade(gb, Env(), torch.ones(3))  # type: ignore[arg-type]
        assert all_finite(res.final, res.reflected_dir)
        if scale == 0.0:
            torch.testing.assert_close(res.reflected_dir, view, rtol=0, atol=1e-6)
            torch.testing.assert_close(
                res.specular, 0.5 * sample_cube(tex, view), rtol=0, atol=1e-6
            )
        res.final.sum().backward()
        assert all_finite(normal.grad)
    torch.testing.assert_close(reflect(view, torch.zeros_like(view)), view, rtol=0, atol=1e-6)
