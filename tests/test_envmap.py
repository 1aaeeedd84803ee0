"""Cube environment map: face convention, seamless bilinear lookup, gradients, guards."""

from __future__ import annotations

import math

import pytest
import torch
from torch.autograd import gradcheck

from core.render.envmap import (
    FACE_NAMES,
    EnvMap,
    direction_to_face_uv,
    pad_cube,
    sample_cube,
    texel_directions,
)

F64 = torch.float64


def smooth_env(d: torch.Tensor) -> torch.Tensor:
    """A smooth RGB function of direction with |gradient| <= 1 on the sphere."""
    d = d / d.norm(dim=-1, keepdim=True)
    x, y, z = d.unbind(-1)
    return torch.stack([1 + 0.5 * x, 1 + 0.5 * y + 0.25 * z * z, 1 + 0.5 * torch.sin(2 * z)], -1)


def face_constants(r: int, dtype=F64) -> torch.Tensor:
    """Face f holds the constant 10 (f + 1) in every texel, 1 channel."""
    c = 10.0 * torch.arange(1, 7, dtype=dtype)
    return c.view(6, 1, 1, 1).expand(6, r, r, 1).clone()


def cube_edges() -> list[tuple[int, int, int, int, int]]:
    """The 12 edges as (axis a, sign a, axis b, sign b, free axis c)."""
    edges = []
    for a in range(3):
        for b in range(a + 1, 3):
            c = 3 - a - b
            for sa in (-1, 1):
                for sb in (-1, 1):
                    edges.append((a, sa, b, sb, c))
    return edges


def edge_points(n: int = 257) -> torch.Tensor:
    """Directions on all 12 edges (corners included), (12 n, 3)."""
    s = torch.linspace(-1, 1, n, dtype=F64)
    out = []
    for a, sa, b, sb, c in cube_edges():
        d = torch.zeros(n, 3, dtype=F64)
        d[:, a], d[:, b], d[:, c] = sa, sb, s
        out.append(d)
    return torch.cat(out)


CORNERS = torch.tensor(
    [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=F64
)


# -- convention -------------------------------------------------------------


def test_face_order_and_orientation_follow_the_opengl_table():
    # The OpenGL spec table (major axis, sc, tc), written out independently of the code.
    x, y, z = 0.3, -0.6, 0.2
    cases = [
        ((1.0, y, z), 0, -z, -y),
        ((-1.0, y, z), 1, z, -y),
        ((x, 1.0, z), 2, x, z),
        ((x, -1.0, z), 3, x, -z),
        ((x, y, 1.0), 4, x, -y),
        ((x, y, -1.0), 5, -x, -y),
    ]
    for d, face, sc, tc in cases:
        f, u, v = direction_to_face_uv(torch.tensor([d], dtype=F64) * 2.5)  # any length
        assert FACE_NAMES[f.item()] == ("+X", "-X", "+Y", "-Y", "+Z", "-Z")[face]
        assert f.item() == face
        assert u.item() == pytest.approx(sc)
        assert v.item() == pytest.approx(tc)


def test_texel_directions_land_on_their_own_texel_centres():
    r = 5
    d = texel_directions(r, F64)
    f, u, v = direction_to_face_uv(d)
    centres = (torch.arange(r, dtype=F64) + 0.5) * 2 / r - 1
    assert torch.equal(f, torch.arange(6).view(6, 1, 1).expand(6, r, r))
    torch.testing.assert_close(u, centres.view(1, 1, r).expand(6, r, r))
    torch.testing.assert_close(v, centres.view(1, r, 1).expand(6, r, r))
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(6, r, r, dtype=F64))


def test_padding_border_is_the_neighbours_adjacent_texel():
    """Every border texel's source lies across the edge, about one texel away."""
    r = 6
    dirs = texel_directions(r, F64)
    padded = pad_cube(dirs)  # pad the directions themselves: border = source direction
    interior = padded[:, 1:-1, 1:-1]
    assert torch.equal(interior, dirs)
    texel_angle = 2 * math.atan(1 / r)  # angular size of a centre texel
    for f in range(6):
        for edge_ref, border in (
            (padded[f, 1, 1:-1], padded[f, 0, 1:-1]),
            (padded[f, -2, 1:-1], padded[f, -1, 1:-1]),
            (padded[f, 1:-1, 1], padded[f, 1:-1, 0]),
            (padded[f, 1:-1, -2], padded[f, 1:-1, -1]),
        ):
            ang = torch.acos((edge_ref * border).sum(-1).clamp(-1, 1))
            assert (ang > 0.2 * texel_angle).all()  # really the other face's texel
            assert (ang < 1.01 * texel_angle).all()
            border_face, _, _ = direction_to_face_uv(border)
            assert (border_face != f).all()


# -- values -----------------------------------------------------------------


@pytest.mark.parametrize("r", [1, 2, 5, 8])
def test_face_centres_and_face_interiors_return_the_face_constant(r):
    tex = face_constants(r)
    axes = torch.tensor(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=F64
    )
    consts = 10.0 * torch.arange(1, 7, dtype=F64)
    out = sample_cube(tex, axes * 3.0).squeeze(-1)
    if r > 1:  # with one texel per face the centre is also half a texel from the edge
        assert torch.equal(out, consts)
    else:
        torch.testing.assert_close(out, consts)
    if r >= 2:
        # away from the edges (more than half a texel) only the face's own texels count
        g = torch.Generator().manual_seed(0)
        d = torch.randn(4000, 3, generator=g, dtype=F64)
        f, u, v = direction_to_face_uv(d)
        inner = (u.abs() < 1 - 1.0 / r) & (v.abs() < 1 - 1.0 / r)
        torch.testing.assert_close(sample_cube(tex, d)[inner].squeeze(-1), consts[f[inner]])


def test_edges_and_corners_blend_the_adjacent_faces_exactly():
    r = 4
    tex = face_constants(r)
    consts = 10.0 * torch.arange(1, 7, dtype=F64)
    # midpoint of each edge: mean of the two faces
    for a, sa, b, sb, _ in cube_edges():
        d = torch.zeros(1, 3, dtype=F64)
        d[0, a], d[0, b] = sa, sb
        fa, fb = 2 * a + (sa < 0), 2 * b + (sb < 0)
        assert sample_cube(tex, d).item() == pytest.approx(0.5 * (consts[fa] + consts[fb]).item())
    # each corner: mean of its three faces, whichever face the lookup picks
    for c in CORNERS:
        faces = [2 * i + int(c[i] < 0) for i in range(3)]
        want = consts[faces].mean().item()
        for scale in (1.0, 1 + 1e-12):  # nudged so that each face wins in turn
            for i in range(3):
                d = c.clone()
                d[i] *= scale
                assert sample_cube(tex, d[None]).item() == pytest.approx(want)


def test_smooth_function_reproduced_everywhere_including_edges_and_corners():
    """Error bound: O(h²) inside faces; within a texel of an edge the border copies sit up
    to half a texel off their true direction, an O(h) error, h = 2/R face-plane units.
    For |∇f| <= 1 the measured constants are 0.86/R² and 0.12/R; we allow 1.5/R², 0.25/R.
    """
    g = torch.Generator().manual_seed(1)
    rand = torch.randn(50_000, 3, generator=g, dtype=F64)
    errs = {}
    for r in (16, 32):
        tex = smooth_env(texel_directions(r, F64))
        err = (sample_cube(tex, rand) - smooth_env(rand)).abs().amax(-1)
        _, u, v = direction_to_face_uv(rand)
        inner = (u.abs() < 1 - 2.0 / r) & (v.abs() < 1 - 2.0 / r)
        assert err[inner].max() < 1.5 / r**2
        assert err.max() < 0.25 / r
        seam = torch.cat([edge_points(), CORNERS])
        seam_err = (sample_cube(tex, seam) - smooth_env(seam)).abs().amax(-1)
        assert seam_err.max() < 0.25 / r
        corner_err = (sample_cube(tex, CORNERS) - smooth_env(CORNERS)).abs()
        assert corner_err.max() < 0.25 / r
        errs[r] = max(err.max().item(), seam_err.max().item())
    assert errs[32] < 0.6 * errs[16]  # converges with resolution


@pytest.mark.parametrize("kind", ["faces", "smooth"])
def test_great_circle_sweeps_across_all_12_edges_have_no_jump(kind):
    """Sweep perpendicular across each edge (at 9 points along it, corners' neighbourhoods
    included) in steps much smaller than a texel: consecutive samples may differ only by
    what bilinear filtering allows (slope <= |Δvalue| per texel), never by a seam jump."""
    r = 16
    if kind == "faces":
        tex = face_constants(r)
        max_slope = 50.0  # largest difference between two face constants, per texel
    else:
        tex = smooth_env(texel_directions(r, F64))
        max_slope = 2.0 / r  # |∇f| <= 1 rad⁻¹, a texel is < 2/R rad
    phi = torch.linspace(-0.08, 0.08, 1601, dtype=F64)
    step = (phi[1] - phi[0]).item()
    cos, sin = phi.cos()[:, None], phi.sin()[:, None]
    texels_per_rad = 1.1 * r  # a texel spans >= 0.94/R rad anywhere on the cube
    allowed = 2.0 * max_slope * step * texels_per_rad
    sweeps = []
    for a, sa, b, sb, c in cube_edges():
        for s in torch.linspace(-0.98, 0.98, 9, dtype=F64):
            p = torch.zeros(3, dtype=F64)
            p[a], p[b], p[c] = sa, sb, s
            t = torch.zeros(3, dtype=F64)
            t[a], t[b] = sa, -sb  # tangent from face b into face a, orthogonal to p
            p, t = p / p.norm(), t / t.norm()
            sweeps.append(cos * p + sin * t)
    vals = sample_cube(tex, torch.stack(sweeps))  # (12 * 9, steps, C)
    jumps = (vals[:, 1:] - vals[:, :-1]).abs().amax(-1).amax(-1)
    assert jumps.max() <= allowed, (jumps.argmax().item(), jumps.max().item())
    if kind == "faces":  # each sweep really crosses from one face value to the other
        assert ((vals[:, 0] - vals[:, -1]).abs() > 5.0).all()


# -- gradients ----------------------------------------------------------------


def test_gradcheck_wrt_texels_including_border_and_corner_paths():
    g = torch.Generator().manual_seed(2)
    tex = torch.rand(6, 4, 4, 2, generator=g, dtype=F64, requires_grad=True)
    dirs = torch.cat(
        [
            torch.randn(12, 3, generator=g, dtype=F64),
            CORNERS,
            edge_points(3),
            torch.tensor([[1.0, 0.3, 0.97], [0.99, -0.995, 0.2]], dtype=F64),
        ]
    )
    assert gradcheck(lambda t: sample_cube(t, dirs), (tex,))
    env = EnvMap(resolution=4, channels=2).double()
    with torch.no_grad():
        env.log_radiance.normal_(generator=g)
    assert gradcheck(lambda lr: sample_cube(torch.exp(lr), dirs), (env.log_radiance,))


def test_gradcheck_wrt_directions_away_from_texel_boundaries():
    g = torch.Generator().manual_seed(3)
    r = 4
    tex = torch.rand(6, r, r, 3, generator=g, dtype=F64, requires_grad=True)
    d = torch.randn(4000, 3, generator=g, dtype=F64)
    d = d * (0.5 + torch.rand(4000, 1, generator=g, dtype=F64))  # not unit length
    _, u, v = direction_to_face_uv(d)
    x, y = (u + 1) * r / 2 + 0.5, (v + 1) * r / 2 + 0.5  # padded coords: kinks at integers

    def away(c):
        return (
            ((c - c.round()).abs() > 0.05) & ((c - 0.5).abs() > 0.05) & ((c - r - 0.5).abs() > 0.05)
        )

    keep = away(x) & away(y) & (u.abs() < 0.97) & (v.abs() < 0.97)
    dirs = d[keep][:40].clone().requires_grad_(True)
    assert dirs.shape[0] == 40
    assert gradcheck(sample_cube, (tex, dirs))


# -- guards -----------------------------------------------------------------


def test_degenerate_directions_give_defined_values_and_finite_gradients():
    r = 4
    tex = torch.rand(6, r, r, 3, dtype=F64, requires_grad=True)
    good = torch.cat([CORNERS, edge_points(3), torch.eye(3, dtype=F64), -torch.eye(3, dtype=F64)])
    inf, nan = float("inf"), float("nan")
    bad = torch.tensor(
        [[0, 0, 0], [nan, 0, 1], [inf, 0, 0], [-inf, inf, 0], [1e-200, 0, 0], [0, -1e-300, 0]],
        dtype=F64,
    )
    dirs = torch.cat([good, bad]).requires_grad_(True)
    out = sample_cube(tex, dirs)
    assert torch.isfinite(out).all()
    assert torch.equal(out[len(good) :], torch.zeros(len(bad), 3, dtype=F64))
    (out * torch.rand_like(out)).sum().backward()
    assert torch.isfinite(tex.grad).all() and torch.isfinite(dirs.grad).all()
    assert torch.equal(dirs.grad[len(good) :], torch.zeros(len(bad), 3, dtype=F64))
    # bad directions contribute nothing to the texel gradient
    tex2 = tex.detach().clone().requires_grad_(True)
    sample_cube(tex2, good).sum().backward()
    tex.grad = None
    sample_cube(tex, dirs).sum().backward()
    torch.testing.assert_close(tex.grad, tex2.grad)
    # a tiny but representable float32 direction still looks up its face
    tiny = torch.tensor([[0.0, 0.0, 1e-12]])
    assert sample_cube(face_constants(2, torch.float32), tiny).item() == 50.0


def test_lookup_is_scale_invariant_and_keeps_batch_shape():
    env = EnvMap(resolution=8, channels=3)
    with torch.no_grad():
        env.log_radiance.normal_()
    d = torch.randn(2, 5, 7, 3)
    out = env(d)
    assert out.shape == (2, 5, 7, 3)
    torch.testing.assert_close(env.sample(d * 7.5), out)
    torch.testing.assert_close(env.sample(d[0, 0]), out[0, 0])
    with pytest.raises(ValueError):
        env.sample(torch.zeros(4, 2))


# -- the module -------------------------------------------------------------


def test_envmap_defaults_activation_and_hdr():
    env = EnvMap()
    assert env.log_radiance.shape == (6, 128, 128, 3)
    assert (env.resolution, env.channels) == (128, 3)
    torch.testing.assert_close(env.texels(), torch.full((6, 128, 128, 3), 0.5))
    assert list(env.state_dict()) == ["log_radiance", "fresnel_logit"]  # the scene F0 too
    small = EnvMap(resolution=4, channels=1, init_value=2.0)
    assert small.log_radiance.shape == (6, 4, 4, 1)
    # HDR values far above 1 and small values round-trip through the activation
    vals = torch.tensor([1e-4, 0.02, 0.5, 1.0, 7.0, 60.0, 2500.0]).repeat(14)[:96]
    small.set_texels(vals.view(6, 4, 4, 1))
    torch.testing.assert_close(small.texels(), vals.view(6, 4, 4, 1), rtol=2e-6, atol=0)
    assert (small.texels() > 0).all()
    # the gradient in log space is the radiance itself: relative steps, dark and bright
    small.texels().sum().backward()
    torch.testing.assert_close(small.log_radiance.grad, small.texels().detach())
    with pytest.raises(ValueError):
        small.set_texels(torch.full((6, 4, 4, 1), float("nan")))
    with pytest.raises(ValueError):
        small.set_texels(torch.ones(6, 4, 4, 3))
    with pytest.raises(ValueError):
        EnvMap(init_value=0.0)
    # zero and absurd radiance stay finite: a floor and a ceiling in log space
    small.set_texels(torch.tensor([0.0, 1e30]).repeat(48).view(6, 4, 4, 1))
    assert torch.isfinite(small.texels()).all() and float(small.texels().detach().min()) > 0


def test_a_softplus_checkpoint_loads_as_the_same_radiance():
    """Env maps saved before log radiance stored ``raw`` with radiance = softplus(raw)."""
    g = torch.Generator().manual_seed(5)
    raw = torch.randn(6, 4, 4, 3, generator=g) * 3.0
    env = EnvMap(resolution=4)
    env.load_state_dict({"raw": raw})
    torch.testing.assert_close(env.texels(), torch.nn.functional.softplus(raw), rtol=1e-5, atol=0)
    from core.model.trained import envmap_from_state

    again = envmap_from_state({"raw": raw}, "cpu")
    assert again is not None and again.resolution == 4
    torch.testing.assert_close(again.texels(), env.texels())
    assert envmap_from_state({"something": raw}, "cpu") is None


def test_training_step_moves_only_the_looked_up_texels():
    env = EnvMap(resolution=8)
    opt = torch.optim.Adam(env.parameters(), lr=0.1)
    d = torch.tensor([[0.0, 0.0, 1.0]])
    target = torch.tensor([[3.0, 2.0, 1.0]])
    before = env.texels().detach().clone()
    for _ in range(80):
        opt.zero_grad()
        loss = (env(d) - target).square().sum()
        loss.backward()
        opt.step()
    after = env.texels().detach()
    assert (env(d) - target).abs().max() < 0.1
    changed = (after - before).abs().amax(-1) > 1e-6
    assert changed[4].sum() == 4 and changed.sum() == 4  # the 4 centre texels of +Z


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    g = torch.Generator().manual_seed(5)
    tex = torch.rand(6, 16, 16, 3, generator=g)
    d = torch.cat([torch.randn(10_000, 3, generator=g), CORNERS.float(), edge_points(9).float()])
    torch.testing.assert_close(sample_cube(tex.cuda(), d.cuda()).cpu(), sample_cube(tex, d))
