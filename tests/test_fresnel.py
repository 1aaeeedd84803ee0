"""Fresnel in the deferred shading: the formula's ends, Schlick's curve under a white
sky, the compiled kernel against the torch path, gradients, and old runs unchanged."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from core.config import TrainConfig, saved_config
from core.model.schedule import phase_at
from core.render.envmap import FRESNEL_MIN_F0, EnvMap
from core.render.fresnel import apply_fresnel, cos_view
from core.render.gbuffer import GBuffer
from core.render.shading import deferred_shade
from core.scene.cameras import Camera, Intrinsics
from tests.test_shading_compiled import _assert_same_shading, _camera, _env, _gbuffer

F64 = torch.float64


def _one_pixel_camera() -> Camera:
    """A 1×1 camera at (0, 0, 4) looking at the origin: its ray is world −z."""
    return Camera.look_at([0, 0, 4.0], [0, 0, 0], [0, 1, 0], Intrinsics(1.0, 1.0, 0.5, 0.5, 1, 1))


def _pixel(cam: Camera, theta_deg: float, f0: float, alpha: float = 1.0, base=0.3, rho=None):
    """One pixel whose unit normal makes ``theta_deg`` with the view ray, coverage
    ``alpha``, un-premultiplied reflectance ``f0``, base colour and roughness."""
    t = math.radians(theta_deg)
    world_n = torch.tensor([[math.sin(t), 0.0, math.cos(t)]], dtype=F64)  # faces the camera
    cam_n = (world_n @ cam.R.to(F64).T).reshape(1, 1, 3)
    a = torch.full((1, 1), alpha, dtype=F64)
    return GBuffer(
        base=torch.full((1, 1, 3), base, dtype=F64) * alpha,
        normal=cam_n * 0.7,  # blended normals are not unit
        plane_dist=torch.zeros(1, 1, dtype=F64),
        w_r=a * f0,
        alpha=a,
        camera=cam,
        roughness=None if rho is None else a * rho,
    )


def _white_sky(value: float = 1.0, f0: float = 0.5) -> EnvMap:
    """A constant sky whose scene F0 (EnvMap.fresnel_f0) is ``f0``."""
    env = EnvMap(4).to(F64)
    env.set_texels(torch.full((6, 4, 4, 3), value, dtype=F64))
    with torch.no_grad():
        u = (f0 - FRESNEL_MIN_F0) / (1 - FRESNEL_MIN_F0)
        env.fresnel_logit.fill_(math.log(u / (1 - u)) if u < 1 else 40.0)
    env.requires_grad_(False)
    return env


def test_cos_view_is_the_angle_to_the_view_ray():
    cam = _one_pixel_camera()
    for theta in (0.0, 30.0, 60.0, 89.0):
        gb = _pixel(cam, theta, 0.2)
        assert cos_view(gb.normal, cam).item() == pytest.approx(math.cos(math.radians(theta)))
    assert cos_view(torch.zeros(1, 1, 3, dtype=F64), cam).item() == 0.0


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("theta", [0.0, 45.0, 70.0, 85.0])
def test_under_a_white_sky_a_coated_surface_follows_schlick(theta, compiled):
    """A dielectric with diffuse colour D and F0 learned as base = (1 − F0)·D, w_r = F0
    (the scene's F0 too): under radiance 1 from every direction the pixel must show
    (1 − F)·D + F with F = F0 + (1 − F0)(1 − cos θ)⁵, the energy split Schlick's curve
    gives; and the same if the map learned the light 10× too bright and w_r 10× too
    small (Eq. 9 fixes only their product) with F0 = 0.04 learned to match."""
    cam, f0, diffuse = _one_pixel_camera(), 0.04, 0.5
    gb = _pixel(cam, theta, f0, base=(1 - f0) * diffuse)
    shade = deferred_shade(
        gb, _white_sky(f0=f0), torch.zeros(3, dtype=F64), compiled=compiled, fresnel=True
    )
    f = f0 + (1 - f0) * (1 - math.cos(math.radians(theta))) ** 5
    want = torch.full((1, 1, 3), (1 - f) * diffuse + f, dtype=F64)
    torch.testing.assert_close(shade.final, want)
    dim = dataclasses.replace(gb, w_r=gb.w_r / 10)  # the light learned 10x too bright
    bright = deferred_shade(
        dim, _white_sky(10.0, f0=f0), torch.zeros(3, dtype=F64), compiled=compiled, fresnel=True
    )
    torch.testing.assert_close(bright.final, want)
    off = deferred_shade(gb, _white_sky(), torch.zeros(3, dtype=F64), compiled=compiled)
    plain = torch.full((1, 1, 3), (1 - f0) * diffuse + f0, dtype=F64)
    torch.testing.assert_close(off.final, plain)


def test_the_ends_head_on_metal_rough_and_grazing():
    cam = _one_pixel_camera()
    bg = torch.zeros(3, dtype=F64)

    def both(gb, f0=0.3):
        sky = _white_sky(2.0, f0=f0)
        return (
            deferred_shade(gb, sky, bg, compiled=False, fresnel=True).final,
            deferred_shade(gb, sky, bg, compiled=False).final,
        )

    on, off = both(_pixel(cam, 0.0, 0.3, alpha=0.6))  # head-on: nothing changes
    torch.testing.assert_close(on, off)
    on, off = both(_pixel(cam, 80.0, 0.3, alpha=0.6, base=0.0), f0=1.0)  # F0 = 1: no rise
    torch.testing.assert_close(on, off)
    on, off = both(_pixel(cam, 80.0, 0.3, alpha=0.6, rho=1.0))  # fully rough: no rise
    torch.testing.assert_close(on, off)
    # edge-on a smooth surface reflects the true light (w_r / F0 · E) and shows no base
    on, _ = both(_pixel(cam, 90.0, 0.15, alpha=0.6, base=0.9))
    torch.testing.assert_close(on, torch.full((1, 1, 3), 0.6 * 0.15 / 0.3 * 2.0, dtype=F64))
    # a rough surface's rise is lowered by 1 − ρ, base and reflection alike
    gb = _pixel(cam, 90.0, 0.15, alpha=0.6, base=0.9)
    base, w = apply_fresnel(gb.base, gb.normal, gb.w_r, 0.25, 0.3, cam)
    assert w.item() == pytest.approx(0.6 * 0.15 * (1 + 0.7 / 0.3 * 0.75))
    assert base[0, 0, 0].item() == pytest.approx(0.6 * 0.9 * 0.25)


def test_the_scene_f0_is_learned_bounded_and_loads_into_old_checkpoints():
    env = EnvMap(4)
    assert "fresnel_logit" in dict(env.named_parameters())  # learned with the map
    half = FRESNEL_MIN_F0 + (1 - FRESNEL_MIN_F0) / 2
    assert float(env.fresnel_f0.detach()) == pytest.approx(half)
    with torch.no_grad():
        env.fresnel_logit.fill_(-1e4)
    assert float(env.fresnel_f0.detach()) == pytest.approx(FRESNEL_MIN_F0)  # the rise stays ≤ 49×
    old = {"log_radiance": torch.zeros(6, 4, 4, 3)}  # a checkpoint from before
    fresh = EnvMap(4)
    fresh.load_state_dict(old)
    assert float(fresh.fresnel_logit.detach()) == 0.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("rough", [False, True])
@pytest.mark.parametrize("seed,res", [(0, 1), (1, 4), (2, 16)])
def test_compiled_fresnel_matches_the_pytorch_path(dtype, seed, res, rough):
    cam = _camera()
    gb = _gbuffer(cam, dtype, seed)
    if rough:
        g = torch.Generator().manual_seed(seed + 10)
        rho = torch.rand(gb.alpha.shape, generator=g, dtype=dtype) * gb.alpha
        gb = dataclasses.replace(gb, roughness=rho)
    env, bg = _env(res, dtype, seed), torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
    with torch.no_grad():
        env.fresnel_logit.fill_(-2.5)  # F0 ≈ 0.1: rims rise up to ~9×
    got = deferred_shade(gb, env, bg, fresnel=True)
    want = deferred_shade(gb, env, bg, compiled=False, fresnel=True)
    _assert_same_shading(got, want, dtype)
    plain = deferred_shade(gb, env, bg, compiled=False)
    assert not torch.allclose(got.final, plain.final)  # the switch does something here


def test_the_training_path_matches_the_reference_and_has_finite_gradients():
    cam = _camera(12, 9)
    gb = _gbuffer(cam, F64, 3)
    g = torch.Generator().manual_seed(5)
    gb = dataclasses.replace(
        gb, roughness=torch.rand(gb.alpha.shape, generator=g, dtype=F64) * gb.alpha
    )
    env, bg = _env(4, F64, 3), torch.zeros(3, dtype=F64)
    env.fresnel_logit.requires_grad_(True)
    leaves = {
        k: getattr(gb, k).clone().requires_grad_(True)
        for k in ("base", "normal", "w_r", "alpha", "roughness")
    }
    train = deferred_shade(
        dataclasses.replace(gb, **leaves), env, bg, fresnel=True
    )  # compiled directions
    ref = deferred_shade(gb, env, bg, compiled=False, fresnel=True)
    torch.testing.assert_close(train.final.detach(), ref.final, rtol=1e-10, atol=1e-12)
    train.final.sum().backward()
    for k, v in leaves.items():
        assert v.grad is not None and torch.isfinite(v.grad).all(), k
    assert env.fresnel_logit.grad is not None and env.fresnel_logit.grad != 0  # F0 learns


def test_apply_fresnel_gradcheck():
    cam = _camera(5, 4)
    g = torch.Generator().manual_seed(1)
    alpha = 0.2 + 0.8 * torch.rand(4, 5, generator=g, dtype=F64)
    base = torch.rand(4, 5, 3, generator=g, dtype=F64) * alpha[..., None]
    normal = torch.randn(4, 5, 3, generator=g, dtype=F64)
    normal[..., 2] = normal[..., 2].abs() + 0.3  # away from c = 0, where |·| has its kink
    w_r = 0.3 * torch.rand(4, 5, generator=g, dtype=F64) * alpha
    rho = 0.3 * torch.rand(4, 5, generator=g, dtype=F64)
    f0 = torch.tensor(0.2, dtype=F64)

    def f(base, normal, w_r, rho, f0):
        return apply_fresnel(base, normal, w_r, rho, f0, cam)

    inputs = tuple(t.clone().requires_grad_(True) for t in (base, normal, w_r, rho, f0))
    assert torch.autograd.gradcheck(f, inputs)


def test_runs_saved_before_fresnel_render_without_it():
    assert TrainConfig().ablation.fresnel is True
    assert saved_config({}).ablation.fresnel is False
    assert saved_config({"ablation": {"roughness": True}}).ablation.fresnel is False
    new = TrainConfig().model_dump(mode="json")
    assert saved_config(new).ablation.fresnel is True
    cfg = TrainConfig(iterations=300)
    assert phase_at(cfg, 299).fresnel is True
    cfg.ablation.fresnel = False
    assert phase_at(cfg, 299).fresnel is False


def test_a_fresnel_model_exports_its_own_f0_to_gltf():
    """A grey metal that reflects 0.6 head-on (its map calibrated: the scene's F0 is
    0.6), seen at grazing angles (κ = 0.2): glTF gets F0 = 0.6 (metallic, c = 0.6), as a
    Fresnel model rises the way glTF's does; a model trained without Fresnel matched
    the views' mean reflectance with its one w_r, which glTF's rising curve reaches from
    a lower F0 (0.5)."""
    import numpy as np

    from core.asset.material import fit_metallic_roughness, fresnel_averaged

    base, w_r, kappa = np.zeros((1, 3)), np.array([0.6]), np.array([0.2])
    b, w = fresnel_averaged(base, w_r, np.zeros(1), kappa, 0.6)
    c, m, res = fit_metallic_roughness(b, w, kappa)
    assert m[0] == pytest.approx(1.0) and c[0] == pytest.approx([0.6] * 3, abs=1e-4)
    assert res[0] < 1e-8
    c_old, _, _ = fit_metallic_roughness(base, w_r, kappa)
    assert c_old[0] == pytest.approx([0.5] * 3, abs=1e-4)
    # a coated plastic: the reflection rises to F and the base gives up 1 − F of D
    b, w = fresnel_averaged(np.full((1, 3), 0.48), np.array([0.04]), np.zeros(1), kappa, 0.04)
    assert w[0] == pytest.approx(0.04 + 0.96 * 0.2)
    assert b[0, 0] == pytest.approx(0.48 * (1 - 0.2))
    # rough: the rise is lowered by 1 − ρ
    _, w = fresnel_averaged(base, np.array([0.04]), np.array([0.5]), kappa, 0.04)
    assert w[0] == pytest.approx(0.04 + 0.96 * 0.2 * 0.5)


def _grads(fn, leaves: dict, weights: tuple) -> tuple:
    out_base, out_w = fn(**leaves)
    ((out_base * weights[0]).sum() + (out_w * weights[1]).sum()).backward()
    grads = {k: v.grad.clone() for k, v in leaves.items() if v is not None and v.grad is not None}
    return out_base.detach(), out_w.detach(), grads


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("rough", [False, True])
@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_rise_matches_the_torch_path_values_and_gradients(dtype, rough, seed):
    """fresnel_compiled against apply_fresnel (with pixel_roughness), every input's
    gradient included, on buffers with uncovered pixels, vanishing and axis normals, and
    roughness past the clamp."""
    from core.render.fresnel_compiled import fresnel_compiled
    from core.render.shading import pixel_roughness

    cam = _camera(23, 17)
    gb = _gbuffer(cam, dtype, seed)
    g = torch.Generator().manual_seed(seed + 3)
    rho = torch.rand(gb.alpha.shape, generator=g, dtype=dtype) * gb.alpha * 1.2  # some > 1
    weights = (
        torch.randn(gb.base.shape, generator=g, dtype=dtype),
        torch.randn(gb.alpha.shape, generator=g, dtype=dtype),
    )

    def leaves(dt):
        out = {
            k: getattr(gb, k).detach().to(dt).clone().requires_grad_(True)
            for k in ("base", "normal", "w_r", "alpha")
        }
        out["roughness"] = rho.to(dt).clone().requires_grad_(True) if rough else None
        out["f0"] = torch.tensor(0.12, dtype=dt, requires_grad=True)
        return out

    def torch_path(base, normal, w_r, alpha, roughness, f0):
        r = 0.0 if roughness is None else pixel_roughness(roughness, alpha)
        return apply_fresnel(base, normal, w_r, r, f0, cam)

    def kernel(base, normal, w_r, alpha, roughness, f0):
        return fresnel_compiled(base, normal, w_r, roughness, alpha, f0, cam)

    # the kernel is float64 inside: float32 is held to the float64 reference (in float32
    # torch's own rounding differs by 3e-4 where the vanishing normals scale by 1e12)
    wide = tuple(w.double() for w in weights)
    b_ref, w_ref, g_ref = _grads(torch_path, leaves(torch.float64), wide)
    b_got, w_got, g_got = _grads(kernel, leaves(dtype), weights)
    b_ref, w_ref, g_ref = (
        b_ref.to(dtype),
        w_ref.to(dtype),
        {k: v.to(dtype) for k, v in g_ref.items()},
    )
    tol = dict(rtol=1e-4, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-9, atol=1e-11)
    torch.testing.assert_close(b_got, b_ref, **tol)
    torch.testing.assert_close(w_got, w_ref, **tol)
    assert set(g_got) == set(g_ref)
    for k in g_ref:
        torch.testing.assert_close(g_got[k], g_ref[k], **tol, msg=k)
