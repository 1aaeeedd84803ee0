"""Plane order (``TrainConfig.splat_order = 'plane'``): each pixel composites its splats in
the order their planes meet its ray; the compiled kernels against the torch reference."""

from __future__ import annotations

import pytest
import torch

from core.config import TrainConfig, saved_config
from core.errors import BackendUnavailableError
from core.model.schedule import phase_at
from core.render.raster import (
    bin_gaussians,
    covariances_from,
    plane_order,
    project_gaussians,
    rasterize,
)
from core.render.raster.plane_order import REACH_SIGMAS, plane_keys
from core.scene.cameras import Camera, Intrinsics
from tests.gsplat_twin import twin_as_cuda  # noqa: F401  (fixture)
from tests.helpers import rot_y


def _camera(w: int = 16, h: int = 16) -> Camera:
    return Camera(
        Intrinsics(float(w), float(w), w / 2, h / 2, w, h), torch.eye(4, dtype=torch.float64)
    )


def _crossing_pair() -> tuple[torch.Tensor, ...]:
    """Two flat splats on parallel planes tilted 45° about the y axis: red (index 0) on
    z = 3.02 + x with its centre at x = −0.1 (centre z 2.92, the nearer centre), blue on
    z = 3 + x with its centre at x = +0.1 (centre z 3.1). On the ray through the image
    centre (x = 0) blue's plane (z = 3) lies in front of red's (z ≈ 3.02)."""
    means = torch.tensor([[-0.1, 0.0, 2.92], [0.1, 0.0, 3.1]], dtype=torch.float64)
    quats = rot_y(-45.0).expand(2, 4).clone()  # normal (−1, 0, 1)/√2
    scales = torch.tensor([[0.3, 0.3, 1e-4]] * 2, dtype=torch.float64)
    op = torch.tensor([0.6, 0.6], dtype=torch.float64)
    feats = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)  # red, blue
    return means, quats, scales, op, feats


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_a_pixel_composites_the_plane_its_ray_meets_first_first(backend: str) -> None:
    means, quats, scales, op, feats = _crossing_pair()
    cam = _camera()
    px = (8, 8)  # pixel centre (8.5, 8.5): its ray passes within 0.1° of the optical axis
    centre = rasterize(means, quats, scales, op, feats, cam, backend=backend)
    red, blue = centre.features[px].tolist()
    # centre order: red (centre z 2.92) first
    a0 = red
    a1 = blue / (1.0 - a0)
    plane = rasterize(means, quats, scales, op, feats, cam, backend=backend, plane_order=True)
    red_p, blue_p = plane.features[px].tolist()
    # plane order: blue first, with the same two alphas
    assert blue_p == pytest.approx(a1, rel=1e-9)
    assert red_p == pytest.approx((1.0 - a1) * a0, rel=1e-9)
    assert blue_p > red_p and red > blue
    torch.testing.assert_close(plane.alpha, centre.alpha)  # coverage does not depend on order


def _flat_splats(
    n: int,
    dtype: torch.dtype,
    seed: int,
    *,
    box: tuple[float, float, float],
    scale: tuple[float, float],
    opacity: tuple[float, float],
    channels: int,
) -> tuple[torch.Tensor, ...]:
    """n flat splats (third scale 1e-3, as trained ones are), centres uniform in a
    ``box`` centred 3 in front of the camera, random rotations, the other scales and
    the opacities uniform in [lo, lo + span), random features."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor(box, dtype=dtype)
    means[:, 2] += 3.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * scale[1] + scale[0]
    scales[:, 2] = 1e-3
    op = torch.rand(n, generator=g, dtype=dtype) * opacity[1] + opacity[0]
    feats = torch.rand(n, channels, generator=g, dtype=dtype)
    return means, quats, scales, op, feats


def _random_scene(n: int, dtype: torch.dtype, seed: int) -> tuple[torch.Tensor, ...]:
    scene = _flat_splats(n, dtype, seed, box=(1.6, 1.4, 1.0), scale=(0.01, 0.1),
                         opacity=(0.0, 0.95), channels=4)  # fmt: skip
    scene[3][:5] = 1.0  # clamped alphas (0.99) pass no gradient to opacity or footprint
    return scene


def _assert_compiled_equals_reference(
    scene: tuple[torch.Tensor, ...],
    cam: Camera,
    tol: float,
    seed: int,
    pixels: torch.Tensor | None = None,
    read: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """The compiled plane order against the reference under a random weighting of every
    output pixel (``read``: the pixels whose features and whose alpha are read; the
    others' upstream gradients are zero):
    features, alpha and every input's gradient; returns the features. ``pixels``: the
    mask both are rendered with."""
    dtype, w, h = scene[0].dtype, cam.intrinsics.width, cam.intrinsics.height
    g = torch.Generator().manual_seed(seed)
    w_feat = torch.rand(h, w, scene[4].shape[1], generator=g, dtype=dtype)
    w_alpha = torch.rand(h, w, generator=g, dtype=dtype)
    if read is not None:
        w_feat, w_alpha = w_feat * read[0][..., None], w_alpha * read[1]
    results = {}
    for backend in ("reference", "cpu"):
        leaves = [t.clone().requires_grad_(True) for t in scene]
        r = rasterize(*leaves, cam, backend=backend, plane_order=True, pixels=pixels)
        ((r.features * w_feat).sum() + (r.alpha * w_alpha).sum()).backward()
        results[backend] = (r.features.detach(), r.alpha.detach(), [t.grad for t in leaves])
    ref, cpu = results["reference"], results["cpu"]
    torch.testing.assert_close(cpu[0], ref[0], atol=tol, rtol=tol)
    torch.testing.assert_close(cpu[1], ref[1], atol=tol, rtol=tol)
    for name, g_cpu, g_ref in zip(("means", "quats", "scales", "opacities", "features"),
                                  cpu[2], ref[2], strict=True):  # fmt: skip
        scale = float(g_ref.abs().max())
        assert scale > 0, name
        torch.testing.assert_close(g_cpu, g_ref, atol=tol * scale * 10, rtol=0, msg=name)
    return cpu[0]


def _kept_tiles(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Record how many tiles each forward kept its runs for."""
    kept: list[int] = []
    forward = plane_order._forward_worker

    def spy(*args):  # the last two arguments are tile_kept and the pixel flags
        forward(*args)
        if args[0] == 0:
            kept.append(args[-2].copy())  # the backward clears it when done

    monkeypatch.setattr(plane_order, "_forward_worker", spy)
    return kept


@pytest.mark.parametrize(
    ("dtype", "tol"), [(torch.float64, 1e-12), (torch.float32, 2e-5)], ids=["f64", "f32"]
)
@pytest.mark.parametrize("store", ["every tile", "no tile", "some tiles"])
def test_compiled_plane_order_equals_the_reference_forward_and_backward(
    dtype: torch.dtype, tol: float, store: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The backward reads the runs the forward kept, or rebuilds a tile's that did not
    fit: both give the reference's gradients."""
    budget = {"every tile": plane_order.RUN_STORE_BYTES, "no tile": 0, "some tiles": 9 * 256 * 12}
    monkeypatch.setattr(plane_order, "RUN_STORE_BYTES", budget[store])
    kept = _kept_tiles(monkeypatch)
    scene = _random_scene(400, dtype, seed=4)
    cam = _camera(48, 40)
    cpu = _assert_compiled_equals_reference(scene, cam, tol, seed=9)
    n_kept = int(kept[0].sum())  # of the 3 × 3 tiles of 16², each with contributors
    assert {"every tile": n_kept == 9, "no tile": n_kept == 0, "some tiles": 0 < n_kept < 9}[
        store
    ], n_kept
    # the scene is one where the order matters: it changes the image
    centre = rasterize(*scene, cam, backend="cpu")
    assert float((centre.features - cpu).abs().max()) > 0.05


@pytest.mark.parametrize("store", ["every tile", "no tile"])
def test_pixels_read_and_pixels_asked_for(store: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A loss that reads a few pixels (the multi-view term) leaves the others' upstream
    gradient at zero, and a caller may ask for a few pixels only: the backward walks (or
    rebuilds) the read ones, the forward composites the asked-for ones, and both still
    give the reference's values and gradients; pixels not asked for come back empty."""
    budget = {"every tile": plane_order.RUN_STORE_BYTES, "no tile": 0}
    monkeypatch.setattr(plane_order, "RUN_STORE_BYTES", budget[store])
    scene = _random_scene(400, torch.float64, seed=5)
    cam = _camera(48, 40)
    g = torch.Generator().manual_seed(3)
    pixels = torch.rand(40, 48, generator=g) < 0.3
    pixels[:16, :16] = False  # one tile asks for nothing
    pixels[16:32, 32:] = True  # one asks for everything
    # some pixels' features are read, some pixels' alpha, some both
    read = tuple(pixels & (torch.rand(40, 48, generator=g) < 0.5) for _ in range(2))
    # a read subset of every pixel, then of the asked-for ones only
    _assert_compiled_equals_reference(scene, cam, 1e-12, seed=2, read=read)
    feats = _assert_compiled_equals_reference(scene, cam, 1e-12, seed=2, pixels=pixels, read=read)
    full = rasterize(*scene, cam, backend="cpu", plane_order=True)
    assert torch.equal(feats[pixels], full.features[pixels])  # exactly what a full frame has
    assert float(full.features[~pixels].abs().max()) > 0.05  # the others had something
    assert float(feats[~pixels].abs().max()) == 0.0
    with pytest.raises(ValueError, match=r"pixels must be \(H, W\) = \(40, 48\)"):
        rasterize(*scene, cam, backend="cpu", plane_order=True, pixels=pixels.T)
    with pytest.raises(ValueError, match=r"pixels must be a bool mask, got dtype torch\.float32"):
        rasterize(*scene, cam, backend="cpu", plane_order=True, pixels=pixels.float())


def _opaque_wall(n: int, dtype: torch.dtype, seed: int) -> tuple[torch.Tensor, ...]:
    """Layers of nearly opaque flat splats filling the whole view: every pixel saturates
    within its first few layers, so most of each tile list lies behind the stop."""
    return _flat_splats(n, dtype, seed, box=(3.6, 3.2, 1.5), scale=(0.08, 0.15),
                        opacity=(0.75, 0.25), channels=3)  # fmt: skip


def _contributors(
    scene: tuple[torch.Tensor, ...], cam: Camera
) -> tuple[torch.Tensor, torch.Tensor]:
    """(H, W) product of (1 - alpha) over every contributor of each pixel, in any order
    (below T_MIN where the compositing stops before the pixel's last contributor), and
    (H, W) how many contributors each pixel has."""
    means, quats, scales, op, _ = (t.detach().double() for t in scene)
    w, h = cam.intrinsics.width, cam.intrinsics.height
    proj = project_gaussians(means, covariances_from(quats, scales), cam)
    bins = bin_gaussians(proj.means2d, proj.depths, proj.radii, w, h, 16)
    v, u = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    T = torch.ones(h, w, dtype=torch.float64)
    count = torch.zeros(h, w, dtype=torch.int64)
    for py in range(h):
        for px in range(w):
            ids = bins.tile((py // 16) * bins.tiles_x + px // 16).long()
            dx = u[py, px] - proj.means2d[ids, 0]
            dy = v[py, px] - proj.means2d[ids, 1]
            c = proj.conics[ids]
            power = -0.5 * (c[:, 0] * dx * dx + c[:, 2] * dy * dy) - c[:, 1] * dx * dy
            alpha = torch.clamp(op[ids] * torch.exp(power.clamp_max(0)), max=0.99)
            live = (power <= 0) & (alpha >= 1 / 255)
            T[py, px] = torch.prod(1 - alpha[live])
            count[py, px] = int(live.sum())
    return T, count


@pytest.mark.parametrize(
    ("dtype", "tol"), [(torch.float64, 1e-12), (torch.float32, 2e-5)], ids=["f64", "f32"]
)
@pytest.mark.parametrize("store", ["every tile", "no tile"])
def test_saturated_pixels_stop_early_and_still_equal_the_reference(
    dtype: torch.dtype, tol: float, store: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The kernels skip what lies behind a saturated pixel's stop (and a tile's whole
    remaining list once all its pixels have stopped): forward and gradients are the
    reference's, which composites every contributor's sorted run."""
    if store == "no tile":
        monkeypatch.setattr(plane_order, "RUN_STORE_BYTES", 0)
    scene = _opaque_wall(2000, dtype, seed=11)
    cam = _camera(48, 40)
    # the case it is written for: (nearly) every pixel saturates
    assert float((_contributors(scene, cam)[0] < 1e-4).double().mean()) > 0.95
    _assert_compiled_equals_reference(scene, cam, tol, seed=3)


def test_a_second_backward_rebuilds_the_runs_the_first_gave_back() -> None:
    """The kept runs' buffers go back to a pool after the backward (the next forward
    overwrites them); a second backward of the same graph rebuilds the runs instead."""
    scene = _random_scene(300, torch.float64, seed=12)
    other = _random_scene(300, torch.float64, seed=13)
    cam = _camera(32, 32)
    leaves = [t.clone().requires_grad_(True) for t in scene]
    r = rasterize(*leaves, cam, backend="cpu", plane_order=True)
    loss = r.features.sum() + r.alpha.sum()
    loss.backward(retain_graph=True)
    first = [t.grad.clone() for t in leaves]
    for t in leaves:
        t.grad = None
    o = rasterize(*[t.clone().requires_grad_(True) for t in other], cam, backend="cpu",
                  plane_order=True)  # fmt: skip
    (o.features.sum() + o.alpha.sum()).backward()  # takes and fills the pooled buffers
    loss.backward()
    for a, b in zip(first, (t.grad for t in leaves), strict=True):
        torch.testing.assert_close(b, a, rtol=1e-12, atol=1e-12)


def test_plane_order_matches_a_pixel_by_pixel_sort_written_out() -> None:
    """Pixels recomputed from first principles: the contributors of the pixel's tile
    list sorted by where the ray meets each plane (clamped to the splat's reach), then
    composited front to back with 3DGS's rules."""
    means, quats, scales, op, feats = _random_scene(200, torch.float64, seed=2)
    cam = _camera(24, 24)
    r = rasterize(means, quats, scales, op, feats, cam, backend="cpu", plane_order=True)
    keys = plane_keys(means, quats, scales, cam)
    proj = project_gaussians(means, covariances_from(quats, scales), cam)
    bins = bin_gaussians(proj.means2d, proj.depths, proj.radii, 24, 24, 16)
    n, d, z, h = keys.planes[:, :3], keys.planes[:, 3], keys.planes[:, 4], keys.planes[:, 5]
    m2d, conic = proj.means2d, proj.conics
    checked = 0
    for py, px in ((12, 12), (5, 17), (20, 3), (9, 9)):
        u, v = px + 0.5, py + 0.5
        ray = torch.tensor([(u - 12.0) / 24.0, (v - 12.0) / 24.0, 1.0], dtype=torch.float64)
        depth_on_ray = torch.minimum(torch.maximum(d / (n @ ray), z - h), z + h)
        dx, dy = u - m2d[:, 0], v - m2d[:, 1]
        power = -0.5 * (conic[:, 0] * dx * dx + conic[:, 2] * dy * dy) - conic[:, 1] * dx * dy
        alpha = torch.clamp(op * torch.exp(power.clamp_max(0)), max=0.99)
        tile = bins.tile((py // 16) * bins.tiles_x + px // 16).tolist()
        live = [i for i in tile if power[i] <= 0 and alpha[i] >= 1 / 255]
        T, out = 1.0, torch.zeros(4, dtype=torch.float64)
        for i in sorted(live, key=lambda i: float(depth_on_ray[i])):
            if T * (1 - float(alpha[i])) < 1e-4:
                break
            out += float(alpha[i]) * T * feats[i]
            T *= 1 - float(alpha[i])
        checked += len(live) > 1
        torch.testing.assert_close(r.features[py, px], out, atol=1e-12, rtol=1e-10)
        assert float(r.alpha[py, px]) == pytest.approx(1 - T, abs=1e-12)
    assert checked >= 3  # pixels with several contributors, where order matters


def test_an_edge_on_splats_key_stays_within_its_reach() -> None:
    """Splats seen edge-on: where the plane contains the ray direction (n·r = 0, so
    d / (n·r) is ±inf or NaN) the key is the centre depth; a plane met arbitrarily far
    away (n·r tiny) is clamped to centre depth ± REACH_SIGMAS × the largest scale."""
    means = torch.tensor([[0.0, 0.0, 2.0], [0.01, 0.0, 2.0]], dtype=torch.float64)
    # normal along x: the planes x = 0 (contains the optical axis) and x = 0.01
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=torch.float64)
    scales = torch.tensor([[1e-4, 0.2, 0.1]] * 2, dtype=torch.float64)
    keys = plane_keys(means, quats, scales, _camera())
    assert keys.planes[:, :3].abs().tolist() == [[1.0, 0.0, 0.0]] * 2
    ids = torch.tensor([0, 1])
    zero = torch.zeros(1, dtype=torch.float64)
    assert keys.keys(ids, zero, zero).tolist() == [[2.0, 2.0]]  # 0/0 and 0.01/0
    tiny = torch.full((1,), 1e-9, dtype=torch.float64)  # n·r = ±1e-9
    reach = REACH_SIGMAS * 0.2
    k = sorted(keys.keys(ids, tiny, zero)[0].tolist())
    # plane x = 0 meets the ray at the camera (depth 0), x = 0.01 at depth 1e7
    assert k == pytest.approx([2.0 - reach, 2.0 + reach])


def test_covariances_give_the_planes_quats_and_scales_give() -> None:
    means, quats, scales, *_ = _random_scene(50, torch.float64, seed=6)
    a = plane_keys(means, quats, scales, _camera())
    b = plane_keys(means, None, None, _camera(), covariances_from(quats, scales))
    # normals agree up to sign; d changes sign with them; z and reach agree
    sign = torch.sign((a.planes[:, :3] * b.planes[:, :3]).sum(-1, keepdim=True))
    torch.testing.assert_close(a.planes[:, :4], b.planes[:, :4] * sign, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(a.planes[:, 4:], b.planes[:, 4:], atol=1e-9, rtol=1e-9)


def test_the_config_switches_plane_order_in_every_phase() -> None:
    cfg = TrainConfig(iterations=100, splat_order="plane")
    assert all(phase_at(cfg, it).splat_order == "plane" for it in (0, 50, 99))


@pytest.mark.usefixtures("twin_as_cuda")
def test_gsplat_refuses_plane_order_with_a_reason() -> None:
    means, quats, scales, op, feats = _crossing_pair()
    with pytest.raises(BackendUnavailableError, match="splat_order 'plane' needs the cpu"):
        rasterize(means, quats, scales, op, feats, _camera(), backend="cuda", plane_order=True)


@pytest.mark.parametrize("store", ["every tile", "no tile"])
def test_tiles_with_more_contributors_than_the_kernels_first_buffers_hold(
    store: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Over a hundred contributors at every pixel (the compiled kernels start with room
    for 64 a pixel; a tile that outgrows it is counted and filled again, in the forward
    and, where it kept nothing, in the backward): the reference's image and gradients."""
    if store == "no tile":
        monkeypatch.setattr(plane_order, "RUN_STORE_BYTES", 0)
    means, quats, scales, op, feats = _random_scene(600, torch.float64, seed=8)
    means[:, :2] *= 0.2  # near the optical axis
    quats[:, 1:] *= 0.3  # facing the camera, tilted at random
    scales[:, :2] = 2.0  # footprints (σ ≈ 10 px) wider than the 16-px image
    op = torch.full_like(op, 0.02)  # each alpha ≤ 0.02: compositing does not stop early
    cam = _camera(16, 16)
    out = {}
    for backend in ("reference", "cpu"):
        leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, op, feats)]
        r = rasterize(*leaves, cam, backend=backend, plane_order=True)
        (r.features.sum() + r.alpha.sum()).backward()
        out[backend] = (r.features.detach(), leaves[3].grad)
    keys = plane_keys(means, quats, scales, cam)
    assert keys.planes.shape == (600, 6)
    torch.testing.assert_close(out["cpu"][0], out["reference"][0], atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(out["cpu"][1], out["reference"][1], atol=1e-10, rtol=1e-8)
    alpha = rasterize(means, quats, scales, op, feats, cam, backend="cpu").alpha
    # 1 − 0.98⁶⁴ = 0.726: every pixel has more than 64 contributors
    assert float(alpha.min()) > 0.75


@pytest.mark.usefixtures("twin_as_cuda")
def test_auto_is_plane_order_where_the_backend_has_it_and_centre_order_on_gsplat() -> None:
    means, quats, scales, op, feats = _crossing_pair()
    cam = _camera()
    kw = {"backend": "cpu"}
    auto = rasterize(means, quats, scales, op, feats, cam, plane_order="auto", **kw)
    plane = rasterize(means, quats, scales, op, feats, cam, plane_order=True, **kw)
    torch.testing.assert_close(auto.features, plane.features, rtol=0, atol=0)
    on_cuda = rasterize(means, quats, scales, op, feats, cam, backend="cuda", plane_order="auto")
    centre = rasterize(means, quats, scales, op, feats, cam, backend="cpu")
    torch.testing.assert_close(on_cuda.features, centre.features, rtol=1e-6, atol=1e-6)
    assert not torch.allclose(plane.features, centre.features, atol=1e-3)


def test_runs_saved_before_plane_order_keep_rendering_in_centre_order() -> None:
    assert TrainConfig().splat_order == "auto"
    old = saved_config(TrainConfig().model_dump(mode="json", exclude={"splat_order"}))
    assert old.splat_order == "centre"
    assert saved_config(TrainConfig(splat_order="plane").model_dump()).splat_order == "plane"
