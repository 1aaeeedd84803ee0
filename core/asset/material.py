"""Eq. 9's material as glTF 2.0 metallic-roughness, under the learned environment.

Glint renders C = base + w_r · E_ρ(r): ``base`` is outgoing radiance that does not
depend on the light (the lighting at training time is baked into it), w_r a scalar
reflection weight and E_ρ the env map prefiltered for roughness ρ. A glTF renderer lit
by the same map E gives, for base colour c, metallic m and roughness ρ (split sum, at
normal incidence, Fresnel F0 = lerp(0.04, c, m)):

    C ≈ (1 − m) · c · Irr(n) · AO  +  lerp(0.04, c, m) · E_ρ(r)

with Irr(n) = (1/π)∫ E(ω) max(0, n·ω) dω the diffuse irradiance and AO the ambient
occlusion (Cycles traces it; rasterisers read the occlusion map). Matching the two per
texel: the diffuse part must give ``base`` → a = base / (Irr · AO) = (1 − m) · c, and
the specular weight must give w_r → 0.04 (1 − m) + m · lum(c) = w_r. Solved for m
(bisection; monotone), then c = a / (1 − m). ρ is glTF's perceptual roughness as is
(Glint's α = ρ², like glTF's GGX).

What is lost: Glint's w_r is colourless and has no Fresnel (glTF's reflectance rises
towards 1 at grazing angles, so rims come out brighter); a w_r below 0.04 becomes 0.04;
a base brighter than the light can explain (a > 1) is clipped; with m = 1 the specular
tint comes from the base's hue; inter-reflections, which Cycles adds, Glint baked into
``base``.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from core.render.envmap import texel_directions

DIELECTRIC_F0 = 0.04
MIN_OCCLUSION = 0.1  # the base colour divides by AO: keep the division bounded
_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float64)


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
    da = (2.0 / r) ** 2 / (1 + s * s + t * t) ** 1.5
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


def solve_metallic(albedo: np.ndarray, w_r: np.ndarray, steps: int = 40) -> np.ndarray:
    """Metallic m per texel with 0.04 (1 − m) + m · lum(clip(a / (1 − m))) = w_r.

    ``albedo`` a (N, 3) is the diffuse part (1 − m) · c the base requires. The left side
    grows with m from 0.04 (m = 0) to lum(clip(a / 0)) (m → 1), so bisection finds the
    root; w_r ≤ 0.04 gives m = 0 and a w_r the left side cannot reach gives m = 1.
    """
    a = np.maximum(albedo.astype(np.float64), 0.0)
    s = np.clip(w_r.astype(np.float64), 0.0, 1.0)

    def f0(m: np.ndarray) -> np.ndarray:
        c = np.clip(a / np.maximum(1.0 - m, 1e-9)[:, None], 0.0, 1.0)
        return DIELECTRIC_F0 * (1 - m) + m * (c @ _LUMA)

    lo = np.zeros_like(s)
    hi = np.ones_like(s)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        below = f0(mid) < s
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    m = 0.5 * (lo + hi)
    m = np.where(f0(np.full_like(s, 1.0 - 1e-9)) < s, 1.0, m)  # no diffuse part can reach it
    m = np.where(s <= DIELECTRIC_F0, 0.0, m)
    return np.clip(m, 0.0, 1.0)


def gltf_material(
    base: np.ndarray,
    w_r: np.ndarray,
    normals: np.ndarray,
    occlusion: np.ndarray | None,
    env_sh: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """(base colour (N, 3) linear in [0, 1], metallic (N,)) for Eq. 9's base and w_r.

    Without an env map (a diffuse plan) there is no light to divide by: the base is
    the colour and the surface a dielectric (metallic 0)."""
    if env_sh is None:
        return np.clip(base, 0.0, 1.0), np.zeros(len(base))
    irr = irradiance(env_sh, normals)
    ao = np.ones(len(base)) if occlusion is None else np.maximum(occlusion, MIN_OCCLUSION)
    albedo = base / (irr * ao[:, None])
    m = solve_metallic(albedo, w_r)
    color = np.clip(albedo / np.maximum(1.0 - m, 1e-9)[:, None], 0.0, 1.0)
    # m = 1: the diffuse part vanishes and c is the specular tint: the base's hue at w_r
    lum = albedo @ _LUMA
    hue = np.where(lum[:, None] > 1e-6, albedo / np.maximum(lum, 1e-6)[:, None], 1.0)
    tint = np.clip(hue * w_r[:, None], 0.0, 1.0)
    full = m >= 1.0 - 1e-6
    color = np.where(full[:, None], tint, color)
    return color, m
