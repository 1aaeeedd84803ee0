"""Singular and extreme covariances: the shapes λ2 = 100 drives every Gaussian towards.

Expected answers (every case, both dtypes, every backend):

* the forward pass (features, alpha) is finite and alpha stays in [0, 0.99·(stack)];
* gradients w.r.t. means, quaternions, scales, opacity logits and features are finite;
* every visible footprint is positive-definite after the low-pass: the stored 2D
  covariance [[a, b], [b, c]] has a > 0, c > 0 and a·c − b² > 0 in exact arithmetic,
  the determinant the projection divides by is > 0 and the conic is finite;
* a zero quaternion renders like the identity rotation with a zero (finite) gradient;
* a saturated opacity (logit +50) is clamped to alpha 0.99, an extinguished one
  (logit −50) draws nothing.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.render.raster import covariances_from, project_gaussians, rasterize
from core.render.raster.projection import ALPHA_MAX
from core.render.rotations import normalize_quats
from tests.stability.common import BACKENDS, all_finite, camera

DTYPES = [torch.float32, torch.float64]
SMALLEST = [0.0, 1e-12, 1e-30]


def _render_and_grad(means, quats, scales, logits, feats, cam, backend):
    """Forward + backward of a loss touching every output; returns (result, grads)."""
    leaves = [
        t.detach().clone().requires_grad_(True) for t in (means, quats, scales, logits, feats)
    ]
    m, q, s, lg, f = leaves
    res = rasterize(m, normalize_quats(q), s, torch.sigmoid(lg), f, cam, backend=backend)
    w = torch.linspace(0.5, 1.5, f.shape[1], dtype=f.dtype)
    loss = (res.features * w).sum() + res.alpha.square().sum()
    if not loss.requires_grad:  # nothing visible: the image is a constant 0
        return res, [torch.zeros_like(t) for t in leaves]
    grads = torch.autograd.grad(loss, leaves, allow_unused=True)
    return res, [
        torch.zeros_like(t) if g is None else g for t, g in zip(leaves, grads, strict=True)
    ]


def _assert_footprints_pd(proj, dtype) -> None:
    vis = proj.visible
    cov = proj.cov2d.detach()[vis].double()  # float32 products are exact in float64
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    assert torch.all(a > 0) and torch.all(c > 0), "filtered 2D covariance must have a, c > 0"
    det = a * c - b * b
    assert torch.all(det > 0), f"stored 2D covariance not positive-definite: min det {det.min()}"
    assert all_finite(proj.conics.detach()[vis]), "conic of a visible Gaussian must be finite"
    assert torch.all(proj.conics.detach()[vis][:, 0] > 0)
    assert torch.all(proj.conics.detach()[vis][:, 2] > 0)


@st.composite
def stiff_gaussians(draw):
    """1–3 Gaussians in front of the camera: singular, needle-like or huge, any rotation."""
    n = draw(st.integers(1, 3))
    rows = []
    for _ in range(n):
        smallest = draw(st.sampled_from(SMALLEST))
        largest = 10 ** draw(st.floats(-3.0, 1.0))
        middle = largest * 10 ** draw(st.floats(-6.0, 0.0))
        if smallest > 0 and draw(st.booleans()):
            largest = smallest * 1e6  # the largest/smallest ratio of the issue
            middle = smallest * 10 ** draw(st.floats(0.0, 6.0))
        scale = [largest, middle, smallest]
        perm = draw(st.permutations([0, 1, 2]))
        quat = draw(
            st.one_of(
                st.just([0.0, 0.0, 0.0, 0.0]),
                st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4),
            )
        )
        mean = [draw(st.floats(-1.5, 1.5)), draw(st.floats(-1.5, 1.5)), draw(st.floats(0.5, 6.0))]
        logit = draw(st.sampled_from([-50.0, 50.0, 0.0, 3.0]))
        rows.append((mean, quat, [scale[i] for i in perm], logit))
    return rows


def _tensors(rows, dtype):
    means = torch.tensor([r[0] for r in rows], dtype=dtype)
    quats = torch.tensor([r[1] for r in rows], dtype=dtype)
    scales = torch.tensor([r[2] for r in rows], dtype=dtype)
    logits = torch.tensor([r[3] for r in rows], dtype=dtype)
    feats = torch.rand(len(rows), 4, generator=torch.Generator().manual_seed(0)).to(dtype)
    return means, quats, scales, logits, feats


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rows=stiff_gaussians(), dtype=st.sampled_from(DTYPES), backend=st.sampled_from(BACKENDS))
def test_stiff_covariances_finite_with_pd_footprints(rows, dtype, backend):
    """Smallest scale 0 / 1e-12 / 1e-30, ratios up to 1e6, zero quaternions, logits ±50:
    finite forward, finite gradients, positive-definite footprints."""
    cam = camera()
    means, quats, scales, logits, feats = _tensors(rows, dtype)
    res, grads = _render_and_grad(means, quats, scales, logits, feats, cam, backend)
    assert all_finite(res.features, res.alpha), "forward pass must be finite"
    assert float(res.alpha.detach().min()) >= 0.0 and float(res.alpha.detach().max()) < 1.0
    names = ("means", "quats", "scales", "opacity_logits", "features")
    for name, g in zip(names, grads, strict=True):
        assert all_finite(g), f"gradient w.r.t. {name} must be finite"
    proj = project_gaussians(means, covariances_from(normalize_quats(quats), scales), cam)
    _assert_footprints_pd(proj, dtype)


def edge_on_covariance(mean: torch.Tensor, roll_deg: float, big: float, smallest: float):
    """Σ (1, 3, 3) float64 of a flat Gaussian whose plane contains the ray to its centre.

    In-plane axes: the ray itself and a direction perpendicular to it, rolled by
    ``roll_deg`` about the ray (so the projected line is not axis-aligned); the normal
    gets ``smallest``. The projected 2D covariance is exactly rank 1.
    """
    r = mean / mean.norm()
    helper = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    u = torch.linalg.cross(r, helper)
    u = u / u.norm()
    v = torch.linalg.cross(r, u)
    th = math.radians(roll_deg)
    t2 = math.cos(th) * u + math.sin(th) * v
    n = torch.linalg.cross(r, t2)
    R = torch.stack([r, t2, n], dim=1)
    s2 = torch.tensor([big, big, smallest], dtype=torch.float64) ** 2
    return ((R * s2) @ R.T)[None]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("smallest", SMALLEST)
def test_edge_on_zero_thickness_footprint_never_culled(dtype, smallest):
    """A flat Gaussian seen exactly edge-on projects to a rank-1 2D covariance; with the
    low-pass it must stay visible and positive-definite for footprints from 1 px to 1e4 px
    (before the fix float32 rounding made a·c − b² ≤ 0 past ~1e3 px and culled it)."""
    cam = camera()
    mean = torch.tensor([0.3, -0.2, 3.0], dtype=torch.float64)
    for roll in (17.0, 45.0, 118.0):
        for footprint_px in (1.0, 10.0, 1e2, 1e3, 3e3, 1e4):
            big = footprint_px * float(mean.norm()) / cam.intrinsics.fx
            cov = edge_on_covariance(mean, roll, big, smallest).to(dtype)
            proj = project_gaussians(mean[None].to(dtype), cov, cam)
            where = f"footprint {footprint_px} px, roll {roll}°"
            assert int(proj.radii[0]) > 0, f"{where}: culled (expected visible)"
            _assert_footprints_pd(proj, dtype)


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_quaternion_is_identity_with_zero_gradient(backend):
    """q = 0 renders exactly like q = (1, 0, 0, 0); its gradient is 0, not NaN."""
    cam = camera()
    means = torch.tensor([[0.1, -0.2, 3.0]])
    scales = torch.tensor([[0.5, 0.2, 0.0]])
    logits = torch.tensor([2.0])
    feats = torch.ones(1, 3)
    zero = torch.zeros(1, 4)
    ident = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    r0, g0 = _render_and_grad(means, zero, scales, logits, feats, cam, backend)
    r1, _ = _render_and_grad(means, ident, scales, logits, feats, cam, backend)
    torch.testing.assert_close(r0.features, r1.features, rtol=0, atol=0)
    torch.testing.assert_close(r0.alpha, r1.alpha, rtol=0, atol=0)
    assert torch.equal(g0[1], torch.zeros_like(g0[1])), "zero quaternion: gradient must be 0"
    assert all_finite(*g0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_saturated_and_extinguished_opacity(backend):
    """Logit +50 (sigmoid = 1 in float32): alpha clamps to 0.99 at the centre and the
    gradient is finite; logit −50 (sigmoid ≈ 2e-22 < 1/255): nothing is drawn."""
    cam = camera()
    means = torch.tensor([[0.0, 0.0, 3.0]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    scales = torch.tensor([[1.0, 1.0, 0.0]])
    feats = torch.ones(1, 3)
    hi, g_hi = _render_and_grad(means, quats, scales, torch.tensor([50.0]), feats, cam, backend)
    assert float(hi.alpha.detach().max()) == pytest.approx(ALPHA_MAX, abs=1e-6)
    assert all_finite(*g_hi)
    lo, g_lo = _render_and_grad(means, quats, scales, torch.tensor([-50.0]), feats, cam, backend)
    assert float(lo.alpha.detach().abs().max()) == 0.0
    assert float(lo.features.detach().abs().max()) == 0.0
    assert all_finite(*g_lo)
