"""Mip chain of the cube env map (core.render.envmap_mips): sizes, box levels, trilinear
lookup (exact at integer levels), seams at every level, roughness → LOD, gradients, guards."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
import torch.nn.functional as F
from torch.autograd import gradcheck

from core.render.envmap import direction_to_face_uv, sample_cube
from core.render.envmap_mips import cube_mip_chain, mip_sizes, roughness_to_lod, sample_cube_lod

F64 = torch.float64


def cube_edges() -> list[tuple[int, int, int, int, int]]:
    """The 12 edges as (axis a, sign a, axis b, sign b, free axis c)."""
    return [
        (a, sa, b, sb, 3 - a - b)
        for a in range(3)
        for b in range(a + 1, 3)
        for sa in (-1, 1)
        for sb in (-1, 1)
    ]


CORNERS = torch.tensor(
    [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=F64
)


def random_cube(r: int, ch: int = 3, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(6, r, r, ch, generator=g, dtype=F64)


def random_dirs(n: int, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=F64)
    return d * (0.5 + torch.rand(n, 1, generator=g, dtype=F64))  # not unit length


# -- the chain --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("r", "sizes"),
    [(16, [16, 8, 4, 2, 1]), (128, [128, 64, 32, 16, 8, 4, 2, 1]), (12, [12, 6, 3]), (7, [7]),
     (1, [1]), (2, [2, 1])],
)  # fmt: skip
def test_chain_sizes(r, sizes):
    assert mip_sizes(r) == sizes
    levels = cube_mip_chain(random_cube(r, ch=2))
    assert [t.shape for t in levels] == [torch.Size((6, n, n, 2)) for n in sizes]


def test_each_level_is_the_2x2_mean_of_the_previous():
    tex = random_cube(16, ch=3)
    levels = cube_mip_chain(tex)
    assert levels[0] is tex
    for prev, cur in itertools.pairwise(levels):
        # avg_pool2d over (6·C, R, R) images: the reference box filter
        want = F.avg_pool2d(prev.permute(0, 3, 1, 2), 2).permute(0, 2, 3, 1)
        torch.testing.assert_close(cur, want, rtol=0, atol=1e-14)
        # and by hand for one texel: rows 2j, 2j+1 × columns 2i, 2i+1
        f, j, i = 3, cur.shape[1] - 1, 0
        by_hand = prev[f, 2 * j : 2 * j + 2, 2 * i : 2 * i + 2].mean(dim=(0, 1))
        torch.testing.assert_close(cur[f, j, i], by_hand, rtol=0, atol=1e-14)
    # the mean radiance of the whole map is the same at every level
    for t in levels:
        torch.testing.assert_close(t.mean(dim=(0, 1, 2)), tex.mean(dim=(0, 1, 2)))


def test_chain_rejects_non_cube_texels():
    with pytest.raises(ValueError, match="cube texels"):
        cube_mip_chain(torch.zeros(6, 4, 2, 3))
    with pytest.raises(ValueError, match="lod"):
        sample_cube_lod(random_cube(4), random_dirs(5), torch.zeros(4, dtype=F64))


# -- the lookup -------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_lod_0_is_sample_cube_exactly(dtype):
    tex = random_cube(8).to(dtype)
    dirs = torch.cat([random_dirs(300), CORNERS, torch.eye(3, dtype=F64)]).to(dtype)
    out = sample_cube_lod(tex, dirs, torch.zeros(dirs.shape[:-1], dtype=dtype), compiled=False)
    assert torch.equal(out, sample_cube(tex, dirs, compiled=False))
    # negative LODs clamp to the sharp level
    low = torch.full(dirs.shape[:-1], -3.0, dtype=dtype)
    assert torch.equal(sample_cube_lod(tex, dirs, low, compiled=False), out)
    # the compiled lookup (float64 inside) to rounding
    fast = sample_cube_lod(tex, dirs, low, compiled=True)
    torch.testing.assert_close(fast, out, rtol=1e-6, atol=1e-6)


def test_integer_lod_is_sample_cube_of_that_level():
    tex = random_cube(16)
    levels = cube_mip_chain(tex)
    dirs = torch.cat([random_dirs(400), CORNERS]).view(2, -1, 3)  # batch shape kept
    for k, level in enumerate(levels):
        lod = torch.full(dirs.shape[:-1], float(k), dtype=F64)
        out = sample_cube_lod(tex, dirs, lod)
        assert out.shape == (*dirs.shape[:-1], 3)
        torch.testing.assert_close(out, sample_cube(level, dirs), rtol=0, atol=1e-13)
    # beyond the last level: the 1×1 level (six face constants, blended at the seams)
    top = sample_cube_lod(tex, dirs, torch.full(dirs.shape[:-1], 99.0, dtype=F64))
    torch.testing.assert_close(top, sample_cube(levels[-1], dirs), rtol=0, atol=1e-13)


def test_fractional_lod_is_linear_between_levels():
    tex = random_cube(8)
    levels = cube_mip_chain(tex)
    dirs = random_dirs(200)
    for lod_value in (0.25, 1.5, 2.75):
        k, t = int(lod_value), lod_value - int(lod_value)
        lod = torch.full(dirs.shape[:-1], lod_value, dtype=F64)
        lo, hi = sample_cube(levels[k], dirs), sample_cube(levels[k + 1], dirs)
        torch.testing.assert_close(sample_cube_lod(tex, dirs, lod), (1 - t) * lo + t * hi)


def test_single_level_maps_read_level_0_at_any_lod():
    tex = random_cube(3)  # odd: no coarser level
    dirs = random_dirs(50)
    for v in (0.0, 0.5, 4.0):
        out = sample_cube_lod(tex, dirs, torch.full((50,), v, dtype=F64))
        torch.testing.assert_close(out, sample_cube(tex, dirs), rtol=0, atol=1e-14)


@pytest.mark.parametrize("lod_value", [0.0, 1.0, 2.0, 3.0, 4.0, 1.4, 3.7])
def test_seamless_across_every_edge_and_corner_at_every_level(lod_value):
    """Directions just either side of each cube edge (9 points along it, near the corners
    too) and just off each corner on its three faces read (almost) the same value: a
    seam would jump by about the texel contrast (O(1) for random texels)."""
    r, eps = 16, 1e-7
    tex = random_cube(r, seed=5)
    pairs_a, pairs_b = [], []
    for a, sa, b, sb, c in cube_edges():
        for s in torch.linspace(-0.999, 0.999, 9, dtype=F64):
            p = torch.zeros(3, dtype=F64)
            p[a], p[b], p[c] = sa, sb, s
            # on face a's side |d_a| > |d_b|, on face b's side the opposite
            pa, pb = p.clone(), p.clone()
            pa[b] = sb * (1 - eps)
            pb[a] = sa * (1 - eps)
            pairs_a.append(pa)
            pairs_b.append(pb)
    da, db = torch.stack(pairs_a), torch.stack(pairs_b)
    fa, _, _ = direction_to_face_uv(da)
    fb, _, _ = direction_to_face_uv(db)
    assert (fa != fb).all()  # each pair really straddles an edge
    lod = torch.full((len(da),), lod_value, dtype=F64)
    va, vb = sample_cube_lod(tex, da, lod), sample_cube_lod(tex, db, lod)
    assert (va - vb).abs().max() < 1e-5

    # corners: nudged into each of the three faces that meet there
    nudged = []
    for corner in CORNERS:
        for axis in range(3):
            d = corner * (1 - eps)
            d[axis] = corner[axis]
            nudged.append(d)
    dc = torch.stack(nudged)
    faces, _, _ = direction_to_face_uv(dc)
    assert len(set(faces.view(8, 3)[0].tolist())) == 3
    vc = sample_cube_lod(tex, dc, torch.full((24,), lod_value, dtype=F64)).view(8, 3, -1)
    assert (vc - vc[:, :1]).abs().max() < 1e-5


# -- roughness → LOD --------------------------------------------------------------------


def test_roughness_to_lod_endpoints_monotonic_and_clamped():
    r = 32
    levels = len(mip_sizes(r))  # 6: 32 … 1
    rho = torch.linspace(0, 1, 501, dtype=F64)
    lod = roughness_to_lod(rho, r, levels)
    assert lod[0] == 0.0
    assert (lod[1:] >= lod[:-1]).all() and (lod[1:101] > lod[:100]).all()
    assert lod.max() == levels - 1 and lod[-1] == levels - 1
    assert lod.min() >= 0
    # out of range roughness is clamped to [0, 1]
    out = roughness_to_lod(torch.tensor([-0.5, 2.0], dtype=F64), r, levels)
    assert out.tolist() == [0.0, float(levels - 1)]
    # the smooth start: flat at ρ = 0 (a mirror reads level 0 with no gradient jump)
    rho0 = torch.zeros(1, dtype=F64, requires_grad=True)
    roughness_to_lod(rho0, r, levels).sum().backward()
    assert rho0.grad.item() == 0.0
    # a single-level map always reads level 0
    assert roughness_to_lod(rho, 7, 1).abs().max() == 0.0


def test_roughness_to_lod_physical_reading():
    """ρ = 0.5 on a 32² map, by hand: α = ρ² = 0.25, the lobe is 4α = 1 rad across;
    x = 4αR / (π/2) = 32 / 1.5708 = 20.372, lod = ½ log2(1 + x²) = ½ log2(416.01) = 4.3502.
    Read back: a level-lod texel spans 2^lod (π/2) / R ≈ 1 rad, the lobe."""
    r, rho = 32, 0.5
    lod = float(roughness_to_lod(torch.tensor(rho, dtype=F64), r, len(mip_sizes(r))))
    assert lod == pytest.approx(4.3502, abs=1e-4)
    alpha = rho**2
    texel_rad = 2.0**lod * (math.pi / 2) / r
    assert texel_rad == pytest.approx(4 * alpha, rel=2e-3)
    # a texel-wide lobe (4α = one level-0 texel) reads level ½ (the smooth start:
    # ½ log2(2)); well above a texel each doubling of α is one level more
    a1 = (math.pi / 2) / r / 4
    alphas = torch.tensor([a1, 8 * a1, 16 * a1], dtype=F64)
    lods = roughness_to_lod(alphas.sqrt(), r, 6)
    assert lods[0].item() == pytest.approx(0.5, abs=1e-9)
    assert (lods[2] - lods[1]).item() == pytest.approx(1.0, abs=0.01)


# -- gradients --------------------------------------------------------------------------


def _away_from_kinks(dirs: torch.Tensor, sizes: list[int], margin: float = 0.05) -> torch.Tensor:
    """Directions whose padded texel coordinates are away from the bilinear kinks (integers
    and the face edges) at every level, and away from the face edges themselves."""
    _, u, v = direction_to_face_uv(dirs)
    keep = (u.abs() < 0.95) & (v.abs() < 0.95)
    for r in sizes:
        for c in ((u + 1) * r / 2 + 0.5, (v + 1) * r / 2 + 0.5):
            keep &= (c - c.round()).abs() > margin
    return keep


def test_gradcheck_texels_directions_and_lod():
    r = 4
    g = torch.Generator().manual_seed(7)
    tex = torch.rand(6, r, r, 2, generator=g, dtype=F64, requires_grad=True)
    d = random_dirs(4000, seed=8)
    keep = _away_from_kinks(d, mip_sizes(r))
    dirs = d[keep][:30].clone().requires_grad_(True)
    assert dirs.shape[0] == 30
    # fractional LODs in each interval (the LOD derivative jumps at integers)
    base = torch.arange(30, dtype=F64) % 2
    lod = (base + 0.1 + 0.8 * torch.rand(30, generator=g, dtype=F64)).requires_grad_(True)
    assert gradcheck(sample_cube_lod, (tex, dirs, lod))
    # texels alone, including the edges, corners and every level
    edge_dirs = torch.cat([CORNERS, torch.eye(3, dtype=F64), random_dirs(12, seed=9)])
    lod_all = torch.linspace(0, 2, len(edge_dirs), dtype=F64)
    assert gradcheck(lambda t: sample_cube_lod(t, edge_dirs, lod_all), (tex,))


def test_lod_gradient_is_the_difference_between_levels():
    tex = random_cube(8)
    levels = cube_mip_chain(tex)
    dirs = random_dirs(20)
    lod = torch.full((20,), 1.3, dtype=F64, requires_grad=True)
    out = sample_cube_lod(tex, dirs, lod)
    out.sum().backward()
    want = (sample_cube(levels[2], dirs) - sample_cube(levels[1], dirs)).sum(-1)
    torch.testing.assert_close(lod.grad, want)


def test_gradient_reaches_level_0_through_coarse_levels():
    tex = random_cube(8).requires_grad_(True)
    dirs = random_dirs(5)
    out = sample_cube_lod(tex, dirs, torch.full((5,), 3.0, dtype=F64))  # the 1×1 level
    out.sum().backward()
    # each level-0 texel of a face reached gets 1/64 of its face's weight
    assert (tex.grad >= 0).all() and tex.grad.sum().item() == pytest.approx(5 * 3)
    touched = tex.grad.sum(dim=(1, 2, 3)) > 0
    for f in touched.nonzero().flatten().tolist():
        face = tex.grad[f, :, :, 0]
        torch.testing.assert_close(face, face[0, 0].expand_as(face))


# -- guards -----------------------------------------------------------------------------


@pytest.mark.parametrize("lod_value", [0.0, 0.6, 1.0, 2.5])
def test_degenerate_directions_give_zero_and_zero_gradient(lod_value):
    r = 4
    tex = random_cube(r).requires_grad_(True)
    good = torch.cat([CORNERS, torch.eye(3, dtype=F64), -torch.eye(3, dtype=F64)])
    inf, nan = float("inf"), float("nan")
    bad = torch.tensor(
        [[0, 0, 0], [nan, 0, 1], [nan, nan, nan], [inf, 0, 0], [-inf, inf, 0], [1e-200, 0, 0]],
        dtype=F64,
    )
    dirs = torch.cat([good, bad]).requires_grad_(True)
    lod = torch.full((len(dirs),), lod_value, dtype=F64, requires_grad=True)
    out = sample_cube_lod(tex, dirs, lod)
    assert torch.isfinite(out).all()
    assert torch.equal(out[len(good) :], torch.zeros(len(bad), 3, dtype=F64))
    (out * torch.rand_like(out)).sum().backward()
    for grad in (tex.grad, dirs.grad, lod.grad):
        assert torch.isfinite(grad).all()
    assert torch.equal(dirs.grad[len(good) :], torch.zeros(len(bad), 3, dtype=F64))
    assert torch.equal(lod.grad[len(good) :], torch.zeros(len(bad), dtype=F64))
    # bad directions add nothing to the texel gradient
    tex2 = tex.detach().clone().requires_grad_(True)
    sample_cube_lod(tex2, good, lod.detach()[: len(good)]).sum().backward()
    tex.grad = None
    sample_cube_lod(tex, dirs, lod.detach()).sum().backward()
    torch.testing.assert_close(tex.grad, tex2.grad)


def test_a_nan_lod_gives_nan_there_and_nothing_else_changes():
    """A NaN roughness (a NaN anywhere in the G-buffer) must reach the loss as NaN, for
    the trainer's guard to skip the step, not index a garbage level."""
    tex = random_cube(8)
    dirs = random_dirs(4)
    lod = torch.tensor([0.5, float("nan"), 1.0, 3.0], dtype=F64)
    out = sample_cube_lod(tex, dirs, lod)
    assert torch.isnan(out[1]).all()
    ok = [0, 2, 3]
    torch.testing.assert_close(out[ok], sample_cube_lod(tex, dirs[ok], lod[ok]))
