"""Compiled deferred shading (Eq. 9) for frames that need no gradient, on the CPU.

Viewer frames and evaluation renders shade every pixel once and never backpropagate.
The PyTorch path (``core.render.shading.deferred_shade``) spends about twenty full-image ops
on it (rays, three normalisations, the reflection, face selection, a four-tap
gather), 86 ms for a 512² frame on one thread, more than splatting the frame. This
kernel does the same arithmetic per pixel in one pass over the image.

Same formulas as ``core.render.shading`` and ``core.render.envmap.sample_cube`` (face table, ties
to the lower axis, padded seamless bilinear taps, zero radiance for a degenerate
direction); intermediate values are float64 and the outputs take the G-buffer's
dtype. ``tests/test_shading_compiled.py`` checks it against the PyTorch path.

Roughness. With a blended roughness the lookup is ``core.render.envmap_mips``'s: ρ is
un-premultiplied by alpha per pixel (``shading.pixel_roughness``), turned into a level
of detail (``roughness_to_lod``), and the two nearest levels of the mip chain are read
with the same padded bilinear taps and blended linearly. The padded levels are packed
in one flat buffer once per frame (first row and padded size of each level). Without
roughness the buffer holds level 0 only and the roughness argument is ``None``, for
which numba compiles a separate specialisation with the LOD code pruned: the same
arithmetic, and the same speed, as before roughness existed.

Fresnel. With ``fresnel_f0`` the pixel's w_r and base are those of
``core.render.fresnel.apply_fresnel`` (cos θ from the normal the reflection uses).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor

from core.kernels.pool import run_ranges
from core.render.envmap import EnvMap
from core.render.envmap_mips import lod_scale
from core.render.envmap_pack_compiled import packed_cube_levels
from core.render.fresnel_compiled import fresnel_rise

__all__ = ["can_shade_compiled", "shade_compiled"]


@njit(nogil=True, cache=True, inline="always")
def _face_st(x, y, z):  # pragma: no cover - numba
    """(face, sc, tc, ma) of direction (x, y, z).

    Face and (sc, tc) as ``core.render.cube_faces.FACE_TABLE``; ties go to the lower axis.
    """
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax >= ay and ax >= az:
        face, ma = (0, ax) if x >= 0 else (1, ax)
        sc, tc = (-z, -y) if x >= 0 else (z, -y)
    elif ay >= az:
        face, ma = (2, ay) if y >= 0 else (3, ay)
        sc, tc = (x, z) if y >= 0 else (x, -z)
    else:
        face, ma = (4, az) if z >= 0 else (5, az)
        sc, tc = (x, -y) if z >= 0 else (-x, -y)
    return face, sc, tc, ma


@njit(nogil=True, cache=True, inline="always")
def _tap(face, sc, tc, ma, offset, p):  # pragma: no cover - numba
    """First flat index and bilinear weights (fx, fy) of the 2×2 taps in a padded level
    of size ``p`` (face size p − 2) whose face 0 starts at flat row ``offset``."""
    res = p - 2
    k = 0.5 * res / ma
    c = 0.5 * res + 0.5
    x = sc * k + c
    y = tc * k + c
    x0 = min(max(math.floor(x), 0.0), p - 2.0)
    y0 = min(max(math.floor(y), 0.0), p - 2.0)
    return offset + face * p * p + int(y0) * p + int(x0), x - x0, y - y0


@njit(nogil=True, cache=True)
def _shade_rows(
    lo, hi, base, normal, w_r, alpha, rough, bg, rot, intr, packed, offsets, sizes,
    lod_scale, min_major, fresnel_f0, final, specular, refl,
):  # fmt: skip  # pragma: no cover - numba
    """Shade pixel rows [lo, hi): final, specular and reflected direction per pixel.

    ``packed`` holds the padded mip levels (level 0 only when ``rough`` is None),
    level k from row ``offsets[k]`` with padded size ``sizes[k]``.
    """
    width = base.shape[1]
    n_ch = packed.shape[-1]
    top_lod = float(offsets.shape[0] - 1)
    lo_max = max(offsets.shape[0] - 2, 0)
    ifx, ify, cx, cy = 1.0 / intr[0], 1.0 / intr[1], intr[2], intr[3]
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    for j in range(lo, hi):
        yc = (j + 0.5 - cy) * ify
        for i in range(width):
            xc = (i + 0.5 - cx) * ifx
            # World view direction R^T (x, y, 1) and world normal R^T n_cam.
            dx = r00 * xc + r10 * yc + r20
            dy = r01 * xc + r11 * yc + r21
            dz = r02 * xc + r12 * yc + r22
            n0, n1, n2 = (
                np.float64(normal[j, i, 0]),
                np.float64(normal[j, i, 1]),
                np.float64(normal[j, i, 2]),
            )
            inv_d = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
            dx, dy, dz = dx * inv_d, dy * inv_d, dz * inv_d
            # A pixel no splat reached (the background: often half a viewer frame) has a
            # zero normal, which reflects the view ray unchanged; skip its arithmetic.
            cos = 0.0  # |view · normal|, for the Fresnel term (a zero normal reads 0)
            if n0 != 0.0 or n1 != 0.0 or n2 != 0.0:
                nx = r00 * n0 + r10 * n1 + r20 * n2
                ny = r01 * n0 + r11 * n1 + r21 * n2
                nz = r02 * n0 + r12 * n1 + r22 * n2
                # safe_normalize twice, as world_normals() and then reflect() apply it:
                # a normal below 1e-12 is scaled by 1e12.
                for _ in range(2):
                    inv_n = 1.0 / math.sqrt(max(nx * nx + ny * ny + nz * nz, 1e-24))
                    nx, ny, nz = nx * inv_n, ny * inv_n, nz * inv_n
                k = 2.0 * (dx * nx + dy * ny + dz * nz)
                cos = min(0.5 * abs(k), 1.0)
                dx, dy, dz = dx - k * nx, dy - k * ny, dz - k * nz  # the reflected direction
            refl[j, i, 0] = dx
            refl[j, i, 1] = dy
            refl[j, i, 2] = dz
            fill = 1.0 - alpha[j, i]
            big = max(abs(dx), abs(dy), abs(dz))
            w = np.float64(w_r[j, i])
            rho = 0.0  # pixel_roughness: read by Fresnel's rise and the LOD alike
            if rough is not None:  # pruned at compile time for a None roughness
                a = np.float64(alpha[j, i])
                rho = np.float64(rough[j, i]) / a if a > 1e-6 else 0.0
                rho = min(rho, 1.0) if rho > 0.0 else 0.0  # NaN reads as a mirror
            keep = 1.0  # the share of the base colour the reflection leaves (Fresnel)
            if fresnel_f0 > 0.0:  # core.render.fresnel.apply_fresnel, per pixel
                rise = fresnel_rise(cos, rho)
                keep = 1.0 - rise
                w = w * (1.0 + (1.0 - fresnel_f0) / fresnel_f0 * rise)
            # w_r = 0 (background, diffuse surfaces) makes the specular term exactly 0:
            # the env map is finite, so the lookup is skipped there.
            if w != 0.0 and math.isfinite(dx + dy + dz) and big > min_major:
                face, sc, tc, ma = _face_st(dx, dy, dz)
                level = 0
                frac = 0.0
                t10, gxw, gyw, q = 0, 0.0, 0.0, 0
                if rough is not None:  # pruned at compile time for a None roughness
                    # roughness_to_lod and sample_cube_lod's LOD split of the pixel's ρ
                    xl = rho * rho * lod_scale
                    lod = min(0.5 * math.log2(1.0 + xl * xl), top_lod)
                    level = min(math.floor(lod), lo_max)  # lod >= 0
                    frac = lod - level
                t00, fxw, fyw = _tap(face, sc, tc, ma, offsets[level], sizes[level])
                p = sizes[level]
                if frac != 0.0:  # a second level (frac = 0 would add 0 to the first)
                    t10, gxw, gyw = _tap(face, sc, tc, ma, offsets[level + 1], sizes[level + 1])
                    q = sizes[level + 1]
                for c in range(n_ch):
                    a00, a01 = packed[t00, c], packed[t00 + 1, c]
                    a10, a11 = packed[t00 + p, c], packed[t00 + p + 1, c]
                    top = a00 + fxw * (a01 - a00)
                    bot = a10 + fxw * (a11 - a10)
                    val = top + fyw * (bot - top)
                    if frac != 0.0:
                        b00, b01 = packed[t10, c], packed[t10 + 1, c]
                        b10, b11 = packed[t10 + q, c], packed[t10 + q + 1, c]
                        top = b00 + gxw * (b01 - b00)
                        bot = b10 + gxw * (b11 - b10)
                        val = val + frac * (top + gyw * (bot - top) - val)
                    spec = w * val
                    specular[j, i, c] = spec
                    final[j, i, c] = base[j, i, c] * keep + spec + fill * bg[c]
            else:
                for c in range(n_ch):
                    specular[j, i, c] = 0.0
                    final[j, i, c] = base[j, i, c] * keep + fill * bg[c]


def can_shade_compiled(tensors: tuple[Tensor, ...], envmap: EnvMap) -> bool:
    """True when the kernel applies: CPU tensors, 3 channels, and no gradient wanted."""
    if not isinstance(envmap, EnvMap):  # any other lookup: only its own sample() knows it
        return False
    params = tuple(envmap.parameters())
    if any(t.device.type != "cpu" for t in (*tensors, *params)):
        return False
    if envmap.channels != tensors[0].shape[-1]:
        return False
    wants_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (*tensors, *params))
    return not wants_grad


def shade_compiled(
    base: Tensor,
    normal: Tensor,
    w_r: Tensor,
    alpha: Tensor,
    bg: Tensor,
    camera,
    envmap: EnvMap,
    roughness: Tensor | None = None,
    *,
    fresnel_f0: float | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """(final, specular, reflected_dir) of one view, as ``deferred_shade`` computes them.

    ``base``/``normal`` (H, W, 3), ``w_r``/``alpha`` (H, W) and ``bg`` (3,) as in the
    G-buffer; ``camera`` is the G-buffer's camera; ``roughness`` (H, W) the G-buffer's
    blended roughness, or None for the sharp lookup; ``fresnel_f0`` the scene's F0 for the
    Fresnel rise (``core.render.fresnel``), None without it.
    No autograd graph is built.
    """
    dtype = base.dtype
    npdt = np.float32 if dtype == torch.float32 else np.float64
    h, w, ch = base.shape

    def arr(t: Tensor) -> np.ndarray:
        return t.detach().to(dtype).numpy()  # strided views are fine: no copies

    with torch.no_grad():
        texels = envmap.texels().detach().to(dtype)
        packed, offsets, sizes = packed_cube_levels(texels, mips=roughness is not None)
    i = camera.intrinsics
    intr = np.array([i.fx, i.fy, i.cx, i.cy], np.float64)
    rot = camera.R.detach().to(torch.float64).contiguous().numpy()
    min_major = math.sqrt(torch.finfo(dtype).tiny)
    scale = lod_scale(texels.shape[1])
    final = np.empty((h, w, ch), npdt)
    specular = np.empty((h, w, ch), npdt)
    refl = np.empty((h, w, 3), npdt)
    args = (
        arr(base), arr(normal), arr(w_r), arr(alpha),
        None if roughness is None else arr(roughness), arr(bg), rot, intr, arr(packed),
        np.array(offsets, np.int64), np.array(sizes, np.int64), scale, min_major,
        -1.0 if fresnel_f0 is None else float(fresnel_f0), final, specular, refl,
    )  # fmt: skip
    run_ranges(_shade_rows, h, args)
    return torch.from_numpy(final), torch.from_numpy(specular), torch.from_numpy(refl)
