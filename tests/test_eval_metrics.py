"""Evaluation metrics against values computed by hand or in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.evaluation.metrics import (
    chamfer_distance,
    lpips_distance,
    lpips_unavailable_reason,
    psnr,
    sample_surface,
    ssim_srgb,
    time_renders,
    to_display,
)


def test_psnr_of_a_2x2_image_by_hand() -> None:
    img = torch.zeros(2, 2, 3)
    ref = torch.zeros(2, 2, 3)
    ref[0, 1] = 0.5  # one pixel off by 0.5 in each channel: MSE = 3·0.25 / 12 = 1/16
    assert psnr(img, ref, display=False) == pytest.approx(10 * math.log10(16.0))
    # sRGB keeps 0 and 1 fixed: one white pixel of four gives MSE = 1/4 on display values
    ref[0, 1] = 1.0
    assert psnr(img, ref) == pytest.approx(10 * math.log10(4.0))
    assert psnr(ref, ref) == math.inf


def _window_mass(n: int, size: int = 11, sigma: float = 1.5) -> np.ndarray:
    """Per pixel, the mass of the 1D Gaussian window that falls inside the image."""
    x = np.arange(size) - (size - 1) / 2
    g = np.exp(-(x**2) / (2 * sigma**2))
    g /= g.sum()
    return np.array(
        [sum(g[k] for k in range(size) if 0 <= i + k - size // 2 < n) for i in range(n)]
    )


def test_ssim_identical_and_constant_images() -> None:
    g = torch.Generator().manual_seed(0)
    img = torch.rand(16, 16, 3, generator=g)
    assert ssim_srgb(img, img) == pytest.approx(1.0, abs=1e-6)
    # Two constant images a, b: with zero padding each pixel sees window mass s = m_i·m_j,
    # mu = a·s, var = a²(s − s²), cov = ab(s − s²): SSIM per pixel in closed form.
    a_lin, b_lin = 0.2, 0.6
    a = float(to_display(torch.tensor(a_lin)))
    b = float(to_display(torch.tensor(b_lin)))
    n = 16
    m = _window_mass(n)
    s = np.outer(m, m)
    c1, c2 = 0.01**2, 0.03**2
    v = s - s * s
    num = (2 * a * b * s * s + c1) * (2 * a * b * v + c2)
    den = ((a * a + b * b) * s * s + c1) * ((a * a + b * b) * v + c2)
    expected = float((num / den).mean())
    # float64: SSIM's E[x²] − μ² cancels badly in float32 (≈1e-4 here)
    x = torch.full((n, n, 3), a_lin, dtype=torch.float64)
    y = torch.full((n, n, 3), b_lin, dtype=torch.float64)
    assert ssim_srgb(x, y) == pytest.approx(expected, rel=1e-7)
    assert ssim_srgb(x.float(), y.float()) == pytest.approx(expected, abs=5e-4)
    # interior pixels (full window) reduce to the luminance term (2ab + C1) / (a² + b² + C1)
    assert expected < (2 * a * b + c1) / (a * a + b * b + c1)


def _square(size: float = 1.0, n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A flat square mesh in the z = 0 plane, centred on the origin (n×n quads)."""
    t = np.linspace(-size / 2, size / 2, n + 1)
    xx, yy = np.meshgrid(t, t, indexing="ij")
    v = np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], 1)
    f = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = (
                i * (n + 1) + j,
                (i + 1) * (n + 1) + j,
                (i + 1) * (n + 1) + j + 1,
                i * (n + 1) + j + 1,
            )
            f += [[a, b, c], [a, c, d]]
    return v, np.array(f)


def test_sampling_is_uniform_by_area() -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [3, 0, 1], [0, 3, 1]], float)
    f = np.array([[0, 1, 2], [3, 4, 5]])  # areas 0.5 and 4.5
    pts, face = sample_surface(v, f, 20000, seed=1)
    assert (face == 1).mean() == pytest.approx(0.9, abs=0.01)
    # points lie on their triangles: z is 0 or 1 and barycentric coordinates are in range
    a, b = pts[face == 0], pts[face == 1]
    assert np.all((a[:, 2] == 0) & (a[:, :2] >= 0).all(1) & (a[:, :2].sum(1) <= 1 + 1e-12))
    assert np.allclose(b[:, 2], 1.0) and np.all(b[:, :2].sum(1) <= 3 + 1e-12)
    # uniform on the triangle: the mean is its centroid
    assert np.allclose(b[:, :2].mean(0), [1.0, 1.0], atol=0.02)


def test_chamfer_against_itself_is_the_sampling_floor() -> None:
    """Two independent uniform samplings of one surface are not at distance 0: for
    densities ρ (points per unit area) the mean nearest-neighbour distance is
    1 / (2√ρ) (Poisson points in the plane), so CD = (1/√ρ_G + 1/√ρ_P) / 4."""
    v, f = _square(1.0)
    n_gt, n_pred = 20000, 80000
    gt, _ = sample_surface(v, f, n_gt, seed=1)
    pred, _ = sample_surface(v, f, n_pred, seed=2)
    res = chamfer_distance(pred, gt)
    floor = (1 / math.sqrt(n_gt) + 1 / math.sqrt(n_pred)) / 4  # area 1
    # boundary effects of the square push it slightly above the infinite-plane value
    assert floor <= res["cd"] <= 1.1 * floor
    assert res["cd_x100"] == pytest.approx(100 * res["cd"])
    assert res["dropped"] == 0 and res["n_pred"] == n_pred
    # and the fraction with a neighbour within t is 1 − exp(−ρπt²) at t = 0.01
    assert res["precision"] == pytest.approx(1 - math.exp(-n_gt * math.pi * 1e-4), abs=1e-3)
    assert res["recall"] > 0.999


def test_chamfer_of_a_shifted_copy_equals_the_shift_and_counts_drops() -> None:
    v, f = _square(1.0)
    gt, _ = sample_surface(v, f, 5000, seed=3)
    normal = np.array([0.0, 0.0, 1.0])
    for shift in (0.004, 0.03):
        # each shifted point's nearest GT point is its own original, at exactly `shift`
        res = chamfer_distance(gt + shift * normal, gt)
        assert res["p2g"] == pytest.approx(shift, rel=1e-9)
        assert res["g2p"] == pytest.approx(shift, rel=1e-9)
        assert res["cd_x100"] == pytest.approx(100 * shift, rel=1e-9)
        assert res["fscore"] == (1.0 if shift < 0.01 else 0.0)
    far = np.array([[0.0, 0.0, 1.2], [2.0, 0.0, 0.0], [0.0, -1.5, 0.5]])
    res = chamfer_distance(np.concatenate([gt + 0.004 * normal, far]), gt)
    assert res["dropped"] == 3 and res["n_pred"] == len(gt)
    assert res["cd"] == pytest.approx(0.004, rel=1e-9)
    kept = chamfer_distance(np.concatenate([gt, far]), gt, max_radius=None)
    assert kept["dropped"] == 0 and kept["p2g"] > 0


def test_chamfer_seen_subset_and_normal_consistency() -> None:
    v, f = _square(1.0)
    gt, _ = sample_surface(v, f, 4000, seed=4)
    seen = gt[:, 0] < 0  # half the GT surface was "seen"
    pred = gt[seen]
    res = chamfer_distance(
        pred,
        gt,
        gt_seen=seen,
        pred_normals=np.tile([0.0, 0.0, -1.0], (len(pred), 1)),  # sign does not matter
        gt_normals=np.tile([0.0, 0.0, 1.0], (len(gt), 1)),
    )
    assert res["cd_seen"] == 0.0 and res["fscore_seen"] == 1.0
    assert res["cd"] > 0.05  # the unseen half is missing from the prediction
    assert res["recall"] == pytest.approx(seen.mean(), abs=0.02)
    assert res["normal_consistency"] == pytest.approx(1.0)


def test_chamfer_protocol_matches_the_data_readme_floor(shared_scene) -> None:
    """Sampling the true teapot mesh with 200k points scores CD×100 ≈ 0.25 (README)."""
    import trimesh

    from core.evaluation.geometry import load_gt_points, mesh_chamfer

    root = shared_scene("teapot_gold")
    mesh = trimesh.load(root / "gt_mesh.ply", process=False, force="mesh")
    gt = load_gt_points(root)
    assert gt is not None and gt["seen"].shape == (len(gt["points"]),)
    res = mesh_chamfer(mesh, gt, n_points=200_000)
    assert res["cd_x100"] == pytest.approx(0.2492, abs=0.01)
    assert res["dropped"] == 0 and res["normal_consistency"] > 0.95


def test_lpips_is_reported_unavailable_never_faked(monkeypatch) -> None:
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "lpips" else real(name, *a)
    )
    reason = lpips_unavailable_reason()
    assert reason is not None and "lpips" in reason
    with pytest.raises(RuntimeError, match="LPIPS unavailable"):
        lpips_distance(torch.zeros(4, 4, 3), torch.zeros(4, 4, 3))


def test_time_renders_reports_the_median_frame() -> None:
    import time

    calls = []

    def render(i: int) -> None:
        calls.append(i)
        time.sleep(0.02 if i != 5 else 0.2)  # one slow frame must not move the median

    res = time_renders(render, 7, warmup=2)
    assert len(calls) == 9 and res["frames"] == 7
    assert 0.018 < res["median_ms"] / 1000 < 0.1
    assert res["fps"] == pytest.approx(1000 / res["median_ms"])
