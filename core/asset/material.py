"""Eq. 9's material as glTF 2.0 metallic-roughness, under the learned environment.

Glint renders C = base + w_r · E_ρ(r): ``base`` is outgoing radiance that does not
depend on the light (the lighting at training time is baked into it), w_r a colourless
reflection weight and E_ρ the learned env map prefiltered for roughness ρ. A glTF
renderer lit by the exported map E gives, for base colour c, metallic m and roughness ρ
(split sum, at normal incidence):

    C ≈ (1 − m) · c · I  +  F0 · E_ρ(r),   F0 = 0.04 (1 − m) + m · c,   I = Irr(n) · AO

with Irr(n) = (1/π)∫E(ω)max(0, n·ω)dω the diffuse irradiance and AO the ambient
occlusion. glTF ties the diffuse colour and the reflection's colour to one c; Eq. 9 does
not (and for a coloured metal the learned map carries the metal's tint: the map is only
ever seen through the object). So per texel (c, m) is the least-squares fit of both
terms, each in units of the light that reaches the texel:

    min  |(1 − m) c I − base|² + |(F − w_r) I|²    over c ∈ [0, 1]³, m ∈ [0, 1]

with F = F0 (1 − κ) + κ glTF's (Schlick) reflectance averaged over the views that saw
the texel (κ their mean (1 − cos θ)⁵): w_r is one value for every angle, glTF's rises
towards 1 at grazing ones. And since Eq. 9 fixes only w_r · E, the map is exported at
the exposure s where this fit is best overall (:func:`gltf_material`).

For fixed m the optimum in c is closed-form per channel; m is searched on a grid and
refined. A grey c (any dielectric with a colourless reflection, a grey metal) is
matched exactly; a coloured base with a strong reflection trades the two, and the fit
says how much it missed. ρ is glTF's perceptual roughness as is (Glint's α = ρ², like
glTF's GGX).

A model trained with Fresnel (``Ablation.fresnel``, ``core.render.fresnel``) rises at
grazing angles too: its own base and reflectance averaged over the same views
(:func:`fresnel_averaged`) are what the fit matches, like for like.

What is lost: the base's colour where the texel is mostly mirror (its F0 must stay
near grey w_r), Fresnel for a model trained without it (glTF's reflectance rises towards
1 at grazing angles, so rims come out brighter), a base brighter than the light can
explain (c > 1 is clipped), inter-reflections that Cycles adds (Glint baked them into ``base``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from core.render.envmap import texel_directions

DIELECTRIC_F0 = 0.04
MIN_OCCLUSION = 0.1  # the base colour divides by AO: keep the division bounded


def _sh9(d: np.ndarray) -> np.ndarray:
    """Real SH basis up to l = 2 at unit directions (N, 3) -> (N, 9)."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return np.stack(
        [
            np.full_like(x, 0.282095),
            0.488603 * y,
            0.488603 * z,
            0.488603 * x,
            1.092548 * x * y,
            1.092548 * y * z,
            0.315392 * (3 * z * z - 1),
            1.092548 * x * z,
            0.546274 * (x * x - y * y),
        ],
        1,
    )


def texel_solid_angles(resolution: int) -> np.ndarray:
    """Solid angle of each cube texel (6, R, R), summing to 4π."""
    r = resolution
    c = (np.arange(r) + 0.5) / r * 2 - 1
    s, t = np.meshgrid(c, c, indexing="xy")
    da = (2.0 / r) ** 2 / (1 + s * s + t * t) ** 1.5  # at the texel centre
    da *= 4 * math.pi / (6 * da.sum())  # exact total: a uniform map's irradiance is exact
    return np.broadcast_to(da, (6, r, r)).copy()


def irradiance_sh(texels: torch.Tensor) -> np.ndarray:
    """SH (9, 3) of the diffuse irradiance Irr(n) = (1/π)∫E(ω)max(0, n·ω)dω of a cube
    map (6, R, R, 3): the radiance projected to l ≤ 2 and convolved with the clamped
    cosine (Ramamoorthi & Hanrahan 2001), divided by π so a white albedo under a
    uniform map of radiance L gives L."""
    t = texels.detach().float().cpu()
    r = t.shape[1]
    dirs = texel_directions(r, torch.float64, "cpu").reshape(-1, 3).numpy()
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    w = texel_solid_angles(r).reshape(-1)
    basis = _sh9(dirs)
    coeffs = (basis * w[:, None]).T @ t.reshape(-1, t.shape[-1]).double().numpy()
    band = np.array([math.pi, *[2 * math.pi / 3] * 3, *[math.pi / 4] * 5])
    return coeffs * band[:, None] / math.pi


def irradiance(sh: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irr at unit normals (N, 3) -> (N, 3), floored at a small positive value."""
    return np.maximum(_sh9(normals.astype(np.float64)) @ sh, 1e-4)


def _best_color(a: np.ndarray, w: np.ndarray, m: np.ndarray, k: np.ndarray) -> np.ndarray:
    """argmin_c |(1 − m)c − a|² + |F(c, m) − w|² per channel, clipped to [0, 1], with
    F = F0 (1 − κ) + κ (a = base / I; separable and convex in each channel)."""
    one, q = 1.0 - m, 1.0 - k
    t = w - k - q * DIELECTRIC_F0 * one
    num = one * a + q * m * t
    den = one * one + q * q * m * m
    return np.clip(num / np.maximum(den, 1e-12), 0.0, 1.0)


def _fit_error(
    a: np.ndarray, w: np.ndarray, m: np.ndarray, c: np.ndarray, k: np.ndarray
) -> np.ndarray:
    one = 1.0 - m
    f = (DIELECTRIC_F0 * one + m * c) * (1.0 - k) + k
    return np.sum((one * c - a) ** 2 + (f - w) ** 2, -1)


def fit_metallic_roughness(
    albedo: np.ndarray,
    w_r: np.ndarray,
    grazing: np.ndarray | None = None,
    grid: int = 41,
    chunk: int = 65536,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(c (N, 3), m (N,), residual (N,)) minimising the fit above for a = base / I (N, 3)
    and w_r (N,): m on a ``grid``-point search, then a local refinement (ternary steps
    within one grid cell). The residual is in units of the light (relative error).

    ``grazing`` κ (N,): the views' mean Schlick term (1 − cos θ)⁵. glTF's reflectance
    at an angle is F0 + (1 − F0)(1 − cos θ)⁵ while w_r is one value for all angles, so
    the fit matches w_r to the reflectance averaged over the views that saw the texel,
    F0 (1 − κ) + κ (None: 0, seen head-on only)."""
    a = np.maximum(albedo.astype(np.float64), 0.0)
    w = np.maximum(w_r.astype(np.float64), 0.0)
    kap = np.zeros(len(a)) if grazing is None else np.clip(grazing.astype(np.float64), 0, 0.99)
    n = len(a)
    out_c = np.empty((n, 3))
    out_m = np.empty(n)
    out_e = np.empty(n)
    ms = np.linspace(0.0, 1.0, grid)
    step = 1.0 / (grid - 1)
    for s0 in range(0, n, chunk):
        sl = slice(s0, min(n, s0 + chunk))
        aa, ww, kk = a[sl][:, None, :], w[sl][:, None, None], kap[sl][:, None, None]
        mm = ms[None, :, None]
        err = _fit_error(aa, ww, mm, _best_color(aa, ww, mm, kk), kk)
        m0 = ms[np.argmin(err, 1)]
        lo, hi = np.maximum(m0 - step, 0.0), np.minimum(m0 + step, 1.0)
        a2, w2, k2 = a[sl], w[sl][:, None], kap[sl][:, None]
        for _ in range(24):  # ternary search: the objective is unimodal near its grid minimum
            m1, m2 = lo + (hi - lo) / 3, hi - (hi - lo) / 3
            e1 = _fit_error(a2, w2, m1[:, None], _best_color(a2, w2, m1[:, None], k2), k2)
            e2 = _fit_error(a2, w2, m2[:, None], _best_color(a2, w2, m2[:, None], k2), k2)
            hi = np.where(e1 <= e2, m2, hi)
            lo = np.where(e1 <= e2, lo, m1)
        m = 0.5 * (lo + hi)
        c = _best_color(a2, w2, m[:, None], k2)
        e = _fit_error(a2, w2, m[:, None], c, k2)
        # the grid point itself when the refinement did not beat it (edges of [0, 1])
        cg = _best_color(a2, w2, m0[:, None], k2)
        eg = _fit_error(a2, w2, m0[:, None], cg, k2)
        better = eg < e
        out_m[sl] = np.where(better, m0, m)
        out_c[sl] = np.where(better[:, None], cg, c)
        out_e[sl] = np.minimum(eg, e)
    return out_c, out_m, out_e


def fresnel_averaged(
    base: np.ndarray,
    w_r: np.ndarray,
    roughness: np.ndarray,
    grazing: np.ndarray,
    f0: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(base (N, 3), w_r (N,)) a Fresnel-trained model shows on average over the views
    that saw each texel: ``core.render.fresnel`` is linear in (1 − cos θ)⁵, so its mean
    is the formula at κ = ``grazing``, the views' mean Schlick term; ``f0`` the scene's
    head-on reflectance (``EnvMap.fresnel_f0``)."""
    rise = (1.0 - np.clip(roughness, 0.0, 1.0)) * np.clip(grazing, 0.0, 1.0)
    return base * (1.0 - rise)[:, None], w_r * (1.0 + (1.0 - f0) / f0 * rise)


ENV_SCALES = np.geomspace(1.0 / 64, 4.0, 33)  # candidate exposures of the exported map
SCALE_SAMPLES = 20000  # texels the exposure is chosen on


def gltf_material(
    base: np.ndarray,
    w_r: np.ndarray,
    normals: np.ndarray,
    occlusion: np.ndarray | None,
    env_sh: np.ndarray | None,
    grazing: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(base colour (N, 3) linear in [0, 1], metallic (N,), relative residual (N,),
    exposure s of the exported map) for Eq. 9's base and w_r under I = Irr(n) · AO.

    Eq. 9 only fixes the product w_r · E: the map's scale is free (w_r / s with s · E
    renders the same) and so is, with it, how much light the base colour answers to.
    glTF's model is not invariant (c ≤ 1, F0 ≤ 1, Fresnel), so the exported map is E · s
    with s the exposure at which the fitted material reproduces the model's radiance
    best: the sum over texels of the absolute error s² I² · residual(s), on a subsample.
    Without an env map (a diffuse plan) there is no light to divide by: the base is the
    colour and the surface a dielectric (metallic 0), s = 1."""
    n = len(base)
    if env_sh is None:
        return np.clip(base, 0.0, 1.0), np.zeros(n), np.zeros(n), 1.0
    irr = irradiance(env_sh, normals)
    ao = np.ones(n) if occlusion is None else np.maximum(occlusion, MIN_OCCLUSION)
    light = irr * ao[:, None]
    a = base / light
    kap = np.zeros(n) if grazing is None else grazing
    pick = np.random.default_rng(0).permutation(n)[:SCALE_SAMPLES]
    weight = np.mean(light[pick] ** 2, 1)

    def cost(scale: float) -> float:
        _, _, res = fit_metallic_roughness(a[pick] / scale, w_r[pick] / scale, kap[pick], grid=21)
        return float(np.sum(scale * scale * weight * res))

    costs = [cost(float(x)) for x in ENV_SCALES]
    best = int(np.argmin(costs))
    lo = np.log(ENV_SCALES[max(best - 1, 0)])
    hi = np.log(ENV_SCALES[min(best + 1, len(ENV_SCALES) - 1)])
    for _ in range(12):  # ternary search in log s between the grid neighbours
        x1, x2 = lo + (hi - lo) / 3, hi - (hi - lo) / 3
        if cost(float(np.exp(x1))) <= cost(float(np.exp(x2))):
            hi = x2
        else:
            lo = x1
    s = float(np.exp(0.5 * (lo + hi)))
    if cost(s) > costs[best]:
        s = float(ENV_SCALES[best])
    c, m, res = fit_metallic_roughness(a / s, w_r / s, kap)
    return c, m, res, s
