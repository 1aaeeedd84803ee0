"""Spherical harmonics: 3DGS constants and signs, orthonormality, rotation behaviour."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from core.render import sh
from core.render.sh import (
    C0,
    C1,
    C2,
    C3,
    eval_sh,
    num_sh_bases,
    rgb_to_sh0,
    sh0_to_rgb,
    sh_basis,
    sh_degree_from_bases,
    sh_to_rgb,
)

PI = math.pi


def test_constants_match_closed_form() -> None:
    # Standard real-SH normalisations; signs as 3DGS folds them into the constants.
    assert C0 == 0.28209479177387814
    r = math.sqrt
    pairs = [
        (C0, 0.5 / r(PI)),
        (C1, r(3 / (4 * PI))),
        (C2[0], 0.5 * r(15 / PI)),
        (C2[1], -0.5 * r(15 / PI)),
        (C2[2], 0.25 * r(5 / PI)),
        (C2[3], -0.5 * r(15 / PI)),
        (C2[4], 0.25 * r(15 / PI)),
        (C3[0], -0.25 * r(35 / (2 * PI))),
        (C3[1], 0.5 * r(105 / PI)),
        (C3[2], -0.25 * r(21 / (2 * PI))),
        (C3[3], 0.25 * r(7 / PI)),
        (C3[4], -0.25 * r(21 / (2 * PI))),
        (C3[5], 0.25 * r(105 / PI)),
        (C3[6], -0.25 * r(35 / (2 * PI))),
    ]
    for i, (actual, expected) in enumerate(pairs):
        assert abs(actual - expected) < 1e-15, i


def test_degree_bookkeeping() -> None:
    assert [num_sh_bases(d) for d in range(4)] == [1, 4, 9, 16]
    assert [sh_degree_from_bases(k) for k in (1, 4, 9, 16)] == [0, 1, 2, 3]
    with pytest.raises(ValueError):
        sh_degree_from_bases(5)
    with pytest.raises(ValueError):
        num_sh_bases(4)


def test_degree0_is_constant() -> None:
    g = torch.Generator().manual_seed(0)
    dirs = torch.randn(100, 3, generator=g)
    coeffs = torch.randn(100, 16, 3, generator=g)
    out = eval_sh(0, coeffs, dirs)
    torch.testing.assert_close(out, C0 * coeffs[:, 0, :])
    # Same coefficients, any direction, same colour.
    same = coeffs[:1].expand(100, 16, 3)
    col = eval_sh(0, same, dirs)
    assert torch.allclose(col, col[:1].expand_as(col))


def _sphere_quadrature(n_theta: int = 8, n_phi: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """Gauss–Legendre in cos θ × uniform in φ: exact for polynomials of degree ≤ 2·n_theta−1
    in z and trigonometric order < n_phi in φ, so products of two degree-≤3 harmonics
    (degree 6) integrate exactly up to rounding."""
    z, wz = np.polynomial.legendre.leggauss(n_theta)
    phi = 2 * PI * np.arange(n_phi) / n_phi
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(1 - zz**2)
    dirs = np.stack([s * np.cos(pp), s * np.sin(pp), zz], axis=-1).reshape(-1, 3)
    w = (wz[:, None] * np.full(n_phi, 2 * PI / n_phi)[None, :]).reshape(-1)
    return torch.from_numpy(dirs), torch.from_numpy(w)


def test_basis_is_orthonormal_quadrature() -> None:
    dirs, w = _sphere_quadrature()
    Y = sh_basis(3, dirs)  # (M, 16) float64
    gram = Y.T @ (Y * w[:, None])
    # Tolerance: the quadrature is exact for these polynomials; only rounding remains.
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=1e-12, rtol=0)


def test_basis_is_orthonormal_monte_carlo() -> None:
    g = torch.Generator().manual_seed(1)
    dirs = torch.randn(400_000, 3, generator=g, dtype=torch.float64)
    Y = sh_basis(3, dirs)
    gram = 4 * PI * (Y.T @ Y) / dirs.shape[0]
    # MC std of ∫Y_iY_j is ≲ 4π·max|Y|²/√M ≈ 0.01; 0.03 is a 3σ-ish bound.
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)


def test_closed_form_values_on_axes() -> None:
    dirs = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    Y = sh_basis(3, dirs)
    zero = 0.0
    expect_z = [C0, zero, C1, zero, zero, zero, 2 * C2[2], zero, zero]
    expect_z += [zero, zero, zero, 2 * C3[3], zero, zero, zero]
    expect_x = [C0, zero, zero, -C1, zero, zero, -C2[2], zero, C2[4]]
    expect_x += [zero, zero, zero, zero, -C3[4], zero, C3[6]]
    expect_y = [C0, -C1, zero, zero, zero, zero, -C2[2], zero, -C2[4]]
    expect_y += [-C3[0], zero, -C3[2], zero, zero, zero, zero]
    expected = torch.tensor([expect_z, expect_x, expect_y], dtype=torch.float64)
    torch.testing.assert_close(Y, expected, atol=1e-14, rtol=0)
    # A diagonal direction: Y_2^{-2} = C2[0]·x·y with x = y = 1/√2, z = 0.
    d = torch.tensor([[1.0, 1.0, 0.0]], dtype=torch.float64)
    assert sh_basis(2, d)[0, 4].item() == pytest.approx(C2[0] * 0.5, abs=1e-14)
    # Y_1 band in 3DGS order is (-C1·y, C1·z, -C1·x).
    d = torch.tensor([[0.6, 0.0, 0.8]], dtype=torch.float64)
    torch.testing.assert_close(
        sh_basis(1, d)[0, 1:], torch.tensor([0.0, C1 * 0.8, -C1 * 0.6], dtype=torch.float64)
    )


def _legendre(l: int, t: torch.Tensor) -> torch.Tensor:
    return [torch.ones_like(t), t, 0.5 * (3 * t**2 - 1), 0.5 * (5 * t**3 - 3 * t)][l]


def test_rotation_addition_theorem() -> None:
    """Σ_m Y_lm(a) Y_lm(b) = (2l+1)/(4π) P_l(a·b): each band transforms as a rotation
    representation (a wrong sign or constant in any basis function breaks this)."""
    g = torch.Generator().manual_seed(2)
    a = torch.randn(64, 3, generator=g, dtype=torch.float64)
    b = torch.randn(64, 3, generator=g, dtype=torch.float64)
    Ya, Yb = sh_basis(3, a), sh_basis(3, b)
    cos = (a / a.norm(dim=1, keepdim=True) * (b / b.norm(dim=1, keepdim=True))).sum(1)
    for l in range(4):
        band = slice(l * l, (l + 1) ** 2)
        lhs = (Ya[:, band] * Yb[:, band]).sum(1)
        rhs = (2 * l + 1) / (4 * PI) * _legendre(l, cos)
        torch.testing.assert_close(lhs, rhs, atol=1e-12, rtol=0)


def test_rotating_direction_and_coefficients_agree() -> None:
    """A degree-1 lobe along z evaluated in a rotated direction equals C1²·cos(angle)."""
    coeffs = torch.zeros(1, 16, 3, dtype=torch.float64)
    coeffs[0, 2, :] = C1  # Y_1 z-term → value C1·C1·d_z
    for angle in (0.0, 0.3, 1.0, PI / 2, 2.5):
        d = torch.tensor([[math.sin(angle), 0.0, math.cos(angle)]], dtype=torch.float64)
        val = eval_sh(3, coeffs, d)[0, 0].item()
        assert val == pytest.approx(C1 * C1 * math.cos(angle), abs=1e-14)


def test_truncation_uses_first_coefficients_only() -> None:
    g = torch.Generator().manual_seed(3)
    dirs = torch.randn(10, 3, generator=g)
    coeffs = torch.randn(10, 16, 3, generator=g)
    for deg in range(4):
        n = num_sh_bases(deg)
        altered = coeffs.clone()
        altered[:, n:] = 1e6  # must be ignored
        torch.testing.assert_close(eval_sh(deg, altered, dirs), eval_sh(deg, coeffs[:, :n], dirs))
    with pytest.raises(ValueError):
        eval_sh(3, coeffs[:, :9], dirs)


def test_direction_scale_invariant_and_zero_safe() -> None:
    g = torch.Generator().manual_seed(4)
    coeffs = torch.randn(5, 16, 3, generator=g)
    dirs = torch.randn(5, 3, generator=g)
    torch.testing.assert_close(eval_sh(3, coeffs, dirs), eval_sh(3, coeffs, 1e-3 * dirs))
    torch.testing.assert_close(eval_sh(3, coeffs, dirs), eval_sh(3, coeffs, 1e4 * dirs))

    zero = torch.zeros(5, 3, requires_grad=True)
    c = coeffs.clone().requires_grad_(True)
    out = eval_sh(3, c, zero)
    # Zero direction: only the DC term (the sphere-averaged colour) survives.
    torch.testing.assert_close(out, C0 * coeffs[:, 0])
    out.sum().backward()
    assert torch.isfinite(zero.grad).all()
    assert torch.isfinite(c.grad).all()


def test_rgb_sh0_round_trip_and_colour_offset() -> None:
    rgb = torch.tensor([[0.0, 0.5, 1.0], [0.2, 0.9, 0.33]])
    torch.testing.assert_close(sh0_to_rgb(rgb_to_sh0(rgb)), rgb)
    assert torch.all(rgb_to_sh0(torch.full((3,), 0.5)) == 0)
    coeffs = torch.zeros(2, 16, 3)
    coeffs[:, 0] = rgb_to_sh0(rgb)
    torch.testing.assert_close(sh_to_rgb(3, coeffs, torch.randn(2, 3)), rgb)
    # Negative colours clamp at 0, values above 1 are not clamped (as 3DGS).
    coeffs[:, 0] = torch.tensor([[-10.0, 0.0, 10.0], [-10.0, 0.0, 10.0]])
    out = sh_to_rgb(0, coeffs, torch.randn(2, 3))
    assert torch.all(out[:, 0] == 0)
    assert torch.all(out[:, 2] > 1)


def test_module_exports_max_degree() -> None:
    assert sh.MAX_SH_DEGREE == 3
