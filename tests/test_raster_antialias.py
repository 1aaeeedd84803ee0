"""Antialiased splatting: opacity × √(det Σ₂ᴰ / det(Σ₂ᴰ + εI)) (Mip-Splatting, gsplat).

Why it matters here: Eq. 7 flattens every Gaussian, so at a silhouette the discs are
seen edge-on; the 0.3 px² low-pass then smears each into a 1-px line of full opacity
outside the object (a dark halo on spot_plastic). The compensation fades them.
"""

from __future__ import annotations

import math

import pytest
import torch

from core.config import config_from_dict
from core.model.schedule import phase_at
from core.render.raster import covariances_from, project_gaussians, rasterize
from core.scene.cameras import Camera, Intrinsics

F64 = torch.float64


def _camera(size: int = 32) -> Camera:
    intr = Intrinsics(30.0, 30.0, size / 2, size / 2, size, size)
    return Camera(intr, torch.eye(4, dtype=F64), "aa")


def _quat_about_y(deg: float) -> torch.Tensor:
    h = math.radians(deg) / 2
    return torch.tensor([[math.cos(h), 0.0, math.sin(h), 0.0]], dtype=F64)


def test_compensation_values():
    cam = _camera()
    means = torch.tensor([[0.0, 0.0, 3.0]] * 3, dtype=F64)
    quats = torch.cat([_quat_about_y(0.0), _quat_about_y(0.0), _quat_about_y(90.0)])
    scales = torch.tensor(
        [[0.5, 0.5, 1e-9], [0.01, 0.01, 1e-9], [0.2, 0.2, 1e-9]], dtype=F64
    )  # wide facing disc, sub-pixel disc, disc seen exactly edge-on
    proj = project_gaussians(means, covariances_from(quats, scales), cam)
    comp = proj.compensation
    assert comp is not None
    # wide: footprint σ² = (30·0.5/3)² = 25 px² per axis → 25 / 25.3
    assert float(comp[0]) == pytest.approx(25.0 / 25.3, rel=1e-6)
    s2 = (30 * 0.01 / 3) ** 2  # 0.01 px²: mostly low-pass
    assert float(comp[1]) == pytest.approx(s2 / (s2 + 0.3), rel=1e-5)
    assert float(comp[2]) < 1e-5  # edge-on: no area, fades out


def test_compensation_matches_gsplat():
    impl = pytest.importorskip("gsplat.cuda._torch_impl")
    g = torch.Generator().manual_seed(3)
    n = 64
    means = torch.randn(n, 3, generator=g, dtype=F64) * 0.4
    means[:, 2] += 3.0
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = torch.rand(n, 3, generator=g, dtype=F64) * 0.05 + 0.002
    scales[::2, 2] = 1e-6
    cam = _camera(40)
    covs = covariances_from(quats, scales)
    proj = project_gaussians(means, covs, cam)
    viewmat = cam.world_to_cam[None]
    K = cam.intrinsics.K(F64)[None]
    _, _, _, _, comp = impl._fully_fused_projection(
        means, covs, viewmat, K, 40, 40, eps2d=0.3, calc_compensations=True
    )
    vis = proj.radii > 0
    torch.testing.assert_close(proj.compensation[vis], comp[0][vis], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_antialiased_is_classic_with_compensated_opacity(backend):
    g = torch.Generator().manual_seed(0)
    n = 80
    means = torch.randn(n, 3, generator=g, dtype=F64) * 0.4
    means[:, 2] += 3.0
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = torch.rand(n, 3, generator=g, dtype=F64) * 0.08 + 0.01
    scales[:, 2] = 1e-7
    opac = torch.rand(n, generator=g, dtype=F64) * 0.8 + 0.1
    feats = torch.rand(n, 4, generator=g, dtype=F64)
    cam = _camera()
    comp = project_gaussians(means, covariances_from(quats, scales), cam).compensation
    aa = rasterize(means, quats, scales, opac, feats, cam, backend=backend, antialiased=True)
    classic = rasterize(means, quats, scales, opac * comp, feats, cam, backend=backend)
    torch.testing.assert_close(aa.features, classic.features)
    torch.testing.assert_close(aa.alpha, classic.alpha)
    plain = rasterize(means, quats, scales, opac, feats, cam, backend=backend)
    assert float((plain.alpha - aa.alpha).min()) >= -1e-12  # compensation only removes cover
    assert float((plain.alpha - aa.alpha).max()) > 1e-3  # and does remove some


def test_edge_on_gradients_stay_finite():
    cam = _camera()
    means = torch.tensor([[0.0, 0.0, 3.0]], dtype=F64, requires_grad=True)
    quats = _quat_about_y(90.0).requires_grad_(True)
    scales = torch.tensor([[0.2, 0.2, 0.0]], dtype=F64, requires_grad=True)
    opac = torch.tensor([0.9], dtype=F64, requires_grad=True)
    feats = torch.ones(1, 3, dtype=F64, requires_grad=True)
    r = rasterize(means, quats, scales, opac, feats, cam, backend="reference", antialiased=True)
    (r.features.sum() + r.alpha.sum()).backward()
    for t in (means, quats, scales, opac, feats):
        assert t.grad is not None and bool(torch.isfinite(t.grad).all())


def test_config_default_and_phase():
    assert config_from_dict({}).antialiased is True
    cfg = config_from_dict({"antialiased": False, "iterations": 100})
    assert phase_at(cfg, 0).antialiased is False
    assert phase_at(config_from_dict({"iterations": 100}), 99).antialiased is True


def test_runs_saved_before_the_field_render_classic():
    from core.config import saved_config

    assert saved_config({"iterations": 10}).antialiased is False
    assert saved_config({"iterations": 10, "antialiased": True}).antialiased is True
