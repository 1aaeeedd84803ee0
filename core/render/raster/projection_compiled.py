"""Fused CPU projection for the "cpu" backend: one compiled pass per Gaussian.

``project_gaussians(means, covariances_from(quats, scales), camera)`` in PyTorch is
~40 small tensor ops (3×3 batched products, clamps, stacks) whose autograd graph
costs more than the compositing kernels at training sizes (128², 20k Gaussians:
~7 ms forward and ~19 ms forward+backward on one core, against ~13 / 39 ms for the
compositing itself). Here quaternion → rotation → Σ = R S² Rᵀ → camera → EWA
Jacobian → 2D covariance with the low-pass → conic, radius and antialiasing
compensation run in one numba loop, and the backward is written out by hand.

The semantics are the reference's (``core.render.raster.projection``), term for term: the
zero quaternion maps to the identity, the Jacobian is evaluated at the centre
clamped to 1.3 × tan(fov/2) past each edge (no gradient through an active clamp),
the 2D covariance is clamped to the PSD cone (the bound on b carries no gradient),
det = det₀ + ε(a₀ + c₀) + ε² with det₀ ≥ 0, and Gaussians outside (near, far), with a
non-finite footprint, or off-screen get radius 0. Arithmetic is float64 whatever
the input dtype, so results match the reference to its own rounding (tested in
``tests/test_projection_compiled.py``), not bit for bit; radii can differ by one pixel
where 3σ falls on an integer. Depths carry no gradient (they only order Gaussians).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor

from core.kernels.pool import run_ranges, store_dtype
from core.render.raster.projection import Projected
from core.scene.cameras import Camera

# Columns of the per-Gaussian state the backward reads back (float64).
_S_QN, _S_ZS, _S_IND, _S_CLX, _S_CLY, _S_A0P, _S_C0P, _S_BP, _S_D0P, _S_OK = range(10)
_N_STATE = 10


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _rotmat(w, x, y, z, R):  # pragma: no cover - numba
    R[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[0, 1] = 2.0 * (x * y - w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[2, 1] = 2.0 * (y * z + w * x)
    R[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _unit_quat(q, i):  # pragma: no cover - numba
    """(w, x, y, z, |q|) of row i, with the identity for a (near) zero quaternion."""
    w, x, y, z = float(q[i, 0]), float(q[i, 1]), float(q[i, 2]), float(q[i, 3])
    qn = math.sqrt(w * w + x * x + y * y + z * z)
    if qn > 1e-12:
        return w / qn, x / qn, y / qn, z / qn, qn
    return 1.0, 0.0, 0.0, 0.0, qn


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _given_cam_cov(covs, Rc, i, Sc, M):  # pragma: no cover - numba
    """Sc = Rc Σᵢ Rcᵀ for a given world covariance (M is scratch)."""
    for r in range(3):
        for k in range(3):
            M[r, k] = (
                Rc[r, 0] * float(covs[i, 0, k])
                + Rc[r, 1] * float(covs[i, 1, k])
                + Rc[r, 2] * float(covs[i, 2, k])
            )
    for r in range(3):
        for c in range(3):
            Sc[r, c] = M[r, 0] * Rc[c, 0] + M[r, 1] * Rc[c, 1] + M[r, 2] * Rc[c, 2]


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _cam_cov(R, s, Rc, i, Sc, M):  # pragma: no cover - numba
    """Sc = Rc (R diag(s²) Rᵀ) Rcᵀ for Gaussian i (R already filled; M is scratch)."""
    for r in range(3):
        for k in range(3):
            acc = 0.0
            for j in range(3):
                acc += Rc[r, j] * R[j, k]
            M[r, k] = acc * float(s[i, k])  # (Rc R S)
    for r in range(3):
        for c in range(3):
            Sc[r, c] = M[r, 0] * M[c, 0] + M[r, 1] * M[c, 1] + M[r, 2] * M[c, 2]


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _load_cam_cov(use_covs, covs, quats, scales, Rc, i, R, Sc, M):  # pragma: no cover
    """Fill Sc (camera-space Σ) for Gaussian i; returns its unit quaternion and |q|
    (the identity and 1 for a given covariance)."""
    if use_covs:
        _given_cam_cov(covs, Rc, i, Sc, M)
        return 1.0, 0.0, 0.0, 0.0, 1.0
    w, qx, qy, qz, qn = _unit_quat(quats, i)
    _rotmat(w, qx, qy, qz, R)
    _cam_cov(R, scales, Rc, i, Sc, M)
    return w, qx, qy, qz, qn


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _centre(means, Rc, tc, i):  # pragma: no cover - numba
    """Camera-space centre (x, y, z) of Gaussian i."""
    mx, my, mz = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
    x = Rc[0, 0] * mx + Rc[0, 1] * my + Rc[0, 2] * mz + tc[0]
    y = Rc[1, 0] * mx + Rc[1, 1] * my + Rc[1, 2] * mz + tc[1]
    z = Rc[2, 0] * mx + Rc[2, 1] * my + Rc[2, 2] * mz + tc[2]
    return x, y, z


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _ewa(x, y, zs, fx, fy, lims, Sc):  # pragma: no cover - numba
    """Clamped centre, EWA Jacobian entries and the unfiltered 2D covariance J Σc Jᵀ."""
    clx = min(max(x / zs, -lims[0]), lims[1])
    cly = min(max(y / zs, -lims[2]), lims[3])
    j00, j11 = fx / zs, fy / zs
    j02, j12 = -fx * clx / zs, -fy * cly / zs  # = -fx·tx/zs², tx = zs·clamp(x/zs)
    a_raw = j00 * j00 * Sc[0, 0] + 2.0 * j00 * j02 * Sc[0, 2] + j02 * j02 * Sc[2, 2]
    b_raw = j00 * j11 * Sc[0, 1] + j00 * j12 * Sc[0, 2] + j02 * j11 * Sc[2, 1]
    b_raw += j02 * j12 * Sc[2, 2]
    c_raw = j11 * j11 * Sc[1, 1] + 2.0 * j11 * j12 * Sc[1, 2] + j12 * j12 * Sc[2, 2]
    return clx, cly, j00, j02, j11, j12, a_raw, b_raw, c_raw


@njit(cache=True, nogil=True, fastmath=False, inline="always")
def _psd_filtered(a_raw, b_raw, c_raw, eps2d, eps_dt):  # pragma: no cover - numba
    """The reference's PSD clamp and low-pass: (a0, c0, lim, b, a, c, a0c0 − b², det0)."""
    a0 = max(a_raw, 0.0)
    c0 = max(c_raw, 0.0)
    lim = math.sqrt(a0 * c0) * (1.0 - 4.0 * eps_dt)
    b = min(max(b_raw, -lim), lim)
    d0_raw = a0 * c0 - b * b
    return a0, c0, lim, b, a0 + eps2d, c0 + eps2d, d0_raw, max(d0_raw, 0.0)


@njit(cache=True, nogil=True, fastmath=False)
def _forward_range(
    lo, hi, means, quats, scales, covs, Rc, tc, intr, lims, params, means2d, conics, depths,
    radii, comp, state,
):  # fmt: skip  # pragma: no cover - numba
    """Project Gaussians lo..hi-1; ``covs`` (N, 3, 3) replaces quats/scales when N > 0."""
    fx, fy, cx, cy, W, H = intr[0], intr[1], intr[2], intr[3], intr[4], intr[5]
    lxn, lxp, lyn, lyp = lims[0], lims[1], lims[2], lims[3]
    near, far, eps2d, eps_dt = params[0], params[1], params[2], params[3]
    use_covs = covs.shape[0] > 0
    keep_state = state.shape[0] > 0
    R = np.empty((3, 3))
    Sc = np.empty((3, 3))
    M = np.empty((3, 3))
    for i in range(lo, hi):
        _, _, _, _, qn = _load_cam_cov(use_covs, covs, quats, scales, Rc, i, R, Sc, M)
        x, y, z = _centre(means, Rc, tc, i)
        in_depth = (z > near) and (z < far)
        zs = z if in_depth else 1.0
        rx, ry = x / zs, y / zs
        _, _, _, _, _, _, a_raw, b_raw, c_raw = _ewa(x, y, zs, fx, fy, lims, Sc)
        a0, c0, lim, b, a, c, d0_raw, det0 = _psd_filtered(a_raw, b_raw, c_raw, eps2d, eps_dt)
        det = det0 + eps2d * (a0 + c0) + eps2d * eps2d
        ok = in_depth and det > 0.0 and math.isfinite(det)
        ds = det if ok else 1.0
        conics[i, 0] = c / ds
        conics[i, 1] = -b / ds
        conics[i, 2] = a / ds
        mid = 0.5 * (a + c)
        lam = mid + math.sqrt(max(mid * mid - ds, 0.1))
        u = fx * x / zs + cx
        v = fy * y / zs + cy
        means2d[i, 0] = u
        means2d[i, 1] = v
        depths[i] = z
        r = 0
        if ok and math.isfinite(u) and math.isfinite(v) and math.isfinite(lam):
            r = math.ceil(3.0 * math.sqrt(lam))
            if not (u + r > 0 and u - r < W and v + r > 0 and v - r < H):
                r = 0
        radii[i] = r
        comp[i] = math.sqrt(max(det0 / ds, 1e-12))
        if keep_state:  # what the backward needs; a gradient-free call skips it
            state[i, _S_QN] = qn
            state[i, _S_ZS] = zs
            state[i, _S_IND] = 1.0 if in_depth else 0.0
            state[i, _S_CLX] = 1.0 if (-lxn <= rx <= lxp) else 0.0
            state[i, _S_CLY] = 1.0 if (-lyn <= ry <= lyp) else 0.0
            state[i, _S_A0P] = 1.0 if a_raw >= 0.0 else 0.0
            state[i, _S_C0P] = 1.0 if c_raw >= 0.0 else 0.0
            state[i, _S_BP] = 1.0 if (-lim <= b_raw <= lim) else 0.0
            state[i, _S_D0P] = 1.0 if d0_raw >= 0.0 else 0.0
            state[i, _S_OK] = 1.0 if ok else 0.0


@njit(cache=True, nogil=True, fastmath=False)
def _backward_range(
    lo, hi, means, quats, scales, covs, Rc, tc, intr, lims, params, state,
    g_m2d, g_con, g_comp, g_means, g_quats, g_scales,
):  # fmt: skip  # pragma: no cover - numba
    """Gradients of Gaussians lo..hi-1; with given ``covs`` only the means get one."""
    fx, fy = intr[0], intr[1]
    eps2d = params[2]
    use_covs = covs.shape[0] > 0
    R = np.empty((3, 3))
    Sc = np.empty((3, 3))
    M = np.empty((3, 3))
    G = np.empty((3, 3))  # dL/dΣ_cam, symmetric
    Gw = np.empty((3, 3))  # dL/dΣ (world), symmetric
    gR = np.empty((3, 3))
    for i in range(lo, hi):
        gu, gv = float(g_m2d[i, 0]), float(g_m2d[i, 1])
        gA, gB, gC = float(g_con[i, 0]), float(g_con[i, 1]), float(g_con[i, 2])
        gk = float(g_comp[i])
        if gu == 0.0 and gv == 0.0 and gA == 0.0 and gB == 0.0 and gC == 0.0 and gk == 0.0:
            continue
        st = state[i]
        w, qx, qy, qz, _ = _load_cam_cov(use_covs, covs, quats, scales, Rc, i, R, Sc, M)
        x, y, _ = _centre(means, Rc, tc, i)
        zs = st[_S_ZS]
        clx, cly, j00, j02, j11, j12, a_raw, b_raw, c_raw = _ewa(x, y, zs, fx, fy, lims, Sc)
        a0, c0, _, b, a, c, _, det0 = _psd_filtered(a_raw, b_raw, c_raw, eps2d, params[3])
        ok = st[_S_OK] > 0.0
        ds = det0 + eps2d * (a0 + c0) + eps2d * eps2d if ok else 1.0
        # conic = (c, -b, a) / ds and comp = sqrt(max(det0 / ds, 1e-12))
        g_a = gC / ds
        g_c = gA / ds
        g_b = -gB / ds
        g_ds = -(gA * c - gB * b + gC * a) / (ds * ds)
        g_det0 = 0.0
        k = math.sqrt(max(det0 / ds, 1e-12))  # the forward's comp, recomputed (same ops)
        if det0 / ds >= 1e-12 and k > 0.0:
            g_r = gk * 0.5 / k
            g_det0 += g_r / ds
            g_ds -= g_r * det0 / (ds * ds)
        if ok:  # ds = det = det0 + eps (a0 + c0) + eps²
            g_det0 += g_ds
            g_a += eps2d * g_ds
            g_c += eps2d * g_ds
        if st[_S_D0P] > 0.0:  # det0 = max(a0 c0 - b², 0)
            g_a += c0 * g_det0
            g_c += a0 * g_det0
            g_b += -2.0 * b * g_det0
        ga_raw = g_a if st[_S_A0P] > 0.0 else 0.0
        gc_raw = g_c if st[_S_C0P] > 0.0 else 0.0
        gb_raw = g_b if st[_S_BP] > 0.0 else 0.0
        # cov2d = J Σc Jᵀ with only (0,0), (0,1), (1,1) read: dL/dΣc and dL/dJ.
        J0 = (j00, 0.0, j02)
        J1 = (0.0, j11, j12)
        for r in range(3):
            for s_ in range(3):
                G[r, s_] = (
                    ga_raw * J0[r] * J0[s_]
                    + 0.5 * gb_raw * (J0[r] * J1[s_] + J1[r] * J0[s_])
                    + gc_raw * J1[r] * J1[s_]
                )
        # dL/dJ = [[2 ga, gb], [gb, 2 gc]] J Σc
        SJ0 = (  # (J Σc) row 0
            j00 * Sc[0, 0] + j02 * Sc[2, 0],
            j00 * Sc[0, 1] + j02 * Sc[2, 1],
            j00 * Sc[0, 2] + j02 * Sc[2, 2],
        )
        SJ1 = (
            j11 * Sc[1, 0] + j12 * Sc[2, 0],
            j11 * Sc[1, 1] + j12 * Sc[2, 1],
            j11 * Sc[1, 2] + j12 * Sc[2, 2],
        )
        gj00 = 2.0 * ga_raw * SJ0[0] + gb_raw * SJ1[0]
        gj02 = 2.0 * ga_raw * SJ0[2] + gb_raw * SJ1[2]
        gj11 = gb_raw * SJ0[1] + 2.0 * gc_raw * SJ1[1]
        gj12 = gb_raw * SJ0[2] + 2.0 * gc_raw * SJ1[2]
        # J → camera-space centre (x, y, zs); tx = zs·clx, j02 = -fx·tx/zs².
        g_x = gu * fx / zs
        g_y = gv * fy / zs
        g_zs = -gu * fx * x / (zs * zs) - gv * fy * y / (zs * zs)
        g_zs += -gj00 * fx / (zs * zs) - gj11 * fy / (zs * zs)
        tx, ty = zs * clx, zs * cly
        g_tx = -gj02 * fx / (zs * zs)
        g_ty = -gj12 * fy / (zs * zs)
        g_zs += gj02 * 2.0 * fx * tx / (zs * zs * zs) + gj12 * 2.0 * fy * ty / (zs * zs * zs)
        px_, py_ = st[_S_CLX], st[_S_CLY]
        g_zs += g_tx * (clx - px_ * x / zs) + g_ty * (cly - py_ * y / zs)
        g_x += g_tx * px_
        g_y += g_ty * py_
        g_z = g_zs if st[_S_IND] > 0.0 else 0.0
        for j in range(3):
            g_means[i, j] = Rc[0, j] * g_x + Rc[1, j] * g_y + Rc[2, j] * g_z
        if use_covs:
            continue
        # Σc = Rc Σ Rcᵀ → dL/dΣ = Rcᵀ G Rc; Σ = M Mᵀ, M = R diag(s) → dL/dM = 2 (dL/dΣ) M.
        for r in range(3):
            for s_ in range(r, 3):
                acc = 0.0
                for p in range(3):
                    for q in range(3):
                        acc += Rc[p, r] * G[p, q] * Rc[q, s_]
                Gw[r, s_] = acc
                Gw[s_, r] = acc
        # dL/dR = 2 dL/dΣ R S². Its isotropic part 2c dL/dΣ R (any c) has no component
        # along rotations (RᵀdL/dΣR is symmetric), so with c = s₀² it is left out: a
        # sphere's quaternion gradient is then exactly 0, not rounding noise that
        # Adam (ε = 1e-15) would turn into full-size steps.
        s0 = float(scales[i, 0])
        c_iso = s0 * s0
        for kk in range(3):
            sk = float(scales[i, kk])
            gs = 0.0
            for r in range(3):
                gRS = 2.0 * (Gw[r, 0] * R[0, kk] + Gw[r, 1] * R[1, kk] + Gw[r, 2] * R[2, kk])
                gR[r, kk] = gRS * (sk * sk - c_iso)
                gs += gRS * sk * R[r, kk]
            g_scales[i, kk] = gs
        gw = 2.0 * (-qz * gR[0, 1] + qy * gR[0, 2] + qz * gR[1, 0] - qx * gR[1, 2])
        gw += 2.0 * (-qy * gR[2, 0] + qx * gR[2, 1])
        gx = 2.0 * (qy * gR[0, 1] + qz * gR[0, 2] + qy * gR[1, 0] - 2.0 * qx * gR[1, 1])
        gx += 2.0 * (-w * gR[1, 2] + qz * gR[2, 0] + w * gR[2, 1] - 2.0 * qx * gR[2, 2])
        gy = 2.0 * (-2.0 * qy * gR[0, 0] + qx * gR[0, 1] + w * gR[0, 2] + qx * gR[1, 0])
        gy += 2.0 * (qz * gR[1, 2] - w * gR[2, 0] + qz * gR[2, 1] - 2.0 * qy * gR[2, 2])
        gz = 2.0 * (-2.0 * qz * gR[0, 0] - w * gR[0, 1] + qx * gR[0, 2] + w * gR[1, 0])
        gz += 2.0 * (-2.0 * qz * gR[1, 1] + qy * gR[1, 2] + qx * gR[2, 0] + qy * gR[2, 1])
        qn = st[_S_QN]
        if qn > 1e-12:
            dot = w * gw + qx * gx + qy * gy + qz * gz
            g_quats[i, 0] = (gw - w * dot) / qn
            g_quats[i, 1] = (gx - qx * dot) / qn
            g_quats[i, 2] = (gy - qy * dot) / qn
            g_quats[i, 3] = (gz - qz * dot) / qn


def _camera_arrays(
    camera: Camera, dtype: torch.dtype, near: float, far: float, eps2d: float
) -> tuple[np.ndarray, ...]:
    intr = camera.intrinsics
    fx, fy, cx, cy, W, H = intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height
    Rc = camera.R.detach().to(torch.float64).contiguous().numpy()
    tc = camera.t.detach().to(torch.float64).contiguous().numpy()
    k = np.array([fx, fy, cx, cy, W, H], np.float64)
    lims = np.array(
        [
            cx / fx + 0.3 * (0.5 * W / fx),
            (W - cx) / fx + 0.3 * (0.5 * W / fx),
            cy / fy + 0.3 * (0.5 * H / fy),
            (H - cy) / fy + 0.3 * (0.5 * H / fy),
        ],
        np.float64,
    )
    params = np.array([near, far, eps2d, torch.finfo(dtype).eps], np.float64)
    return Rc, tc, k, lims, params


class CompiledProjection(torch.autograd.Function):
    """(means, quats, scales | covs) → (means2d, conics, compensation); depths and radii
    ride along. Given covariances get no gradient (callers check)."""

    @staticmethod
    def forward(ctx, means, quats, scales, covs, camera, near, far, eps2d):
        dtype = means.dtype
        n = means.shape[0]
        m = means.detach().contiguous().numpy()
        if covs is None:
            q = quats.detach().contiguous().numpy()
            s = scales.detach().contiguous().numpy()
            c = np.empty((0, 3, 3), np.float64)
        else:
            q = np.empty((0, 4), np.float64)
            s = np.empty((0, 3), np.float64)
            c = covs.detach().contiguous().numpy()
        cam = _camera_arrays(camera, dtype, near, far, eps2d)
        # outputs in the inputs' dtype: the kernel rounds its float64 values on store,
        # as a conversion afterwards would (four passes over (N, ·) arrays saved)
        npdt = store_dtype(dtype)
        means2d = np.empty((n, 2), npdt)
        conics = np.empty((n, 3), npdt)
        depths = np.empty(n, npdt)
        radii = np.empty(n, np.int64)
        comp = np.empty(n, npdt)
        # Only a backward reads the state (80 bytes a Gaussian): skip it without one.
        keep = any(ctx.needs_input_grad[:4])
        state = np.empty((n if keep else 0, _N_STATE), np.float64)
        args = (m, q, s, c, *cam, means2d, conics, depths, radii, comp, state)
        run_ranges(_forward_range, n, args)
        # The numpy views alias the inputs: saving them makes autograd refuse a backward
        # after an in-place change instead of silently using the new values.
        ctx.save_for_backward(means, quats, scales, covs)
        ctx.arrays = (m, q, s, c, cam, state)
        ctx.dtypes = (means.dtype, None if quats is None else quats.dtype,
                      None if scales is None else scales.dtype)  # fmt: skip
        out = [torch.from_numpy(a).to(dtype) for a in (means2d, conics, comp, depths)]
        radii_t = torch.from_numpy(radii)
        ctx.mark_non_differentiable(out[3], radii_t)
        return out[0], out[1], out[2], out[3], radii_t

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_m2d, g_con, g_comp, _g_depth, _g_radii):
        ctx.saved_tensors  # noqa: B018  (raises if an input was modified in place)
        m, q, s, c, cam, state = ctx.arrays
        n = m.shape[0]

        def arr(g: Tensor | None, shape: tuple[int, ...]) -> np.ndarray:
            # float32 as it comes: the kernel widens each value exactly
            if g is None:
                return np.zeros(shape, np.float64)
            g = g.detach()
            if g.dtype not in (torch.float32, torch.float64):
                g = g.to(torch.float64)
            return g.contiguous().numpy()

        d_means, d_quats, d_scales = ctx.dtypes
        # gradients in their parameters' dtype, rounded on store (see forward)
        gm = np.zeros((n, 3), store_dtype(d_means))
        gq = np.zeros((n, 4), store_dtype(d_quats))
        gs = np.zeros((n, 3), store_dtype(d_scales))
        args = (
            m, q, s, c, *cam, state,
            arr(g_m2d, (n, 2)), arr(g_con, (n, 3)), arr(g_comp, (n,)), gm, gq, gs,
        )  # fmt: skip
        run_ranges(_backward_range, n, args)
        need = ctx.needs_input_grad
        return (
            torch.from_numpy(gm).to(d_means) if need[0] else None,
            torch.from_numpy(gq).to(d_quats) if need[1] else None,
            torch.from_numpy(gs).to(d_scales) if need[2] else None,
            None,
            None,
            None,
            None,
            None,
        )


def project_compiled(
    means: Tensor,
    quats: Tensor | None,
    scales: Tensor | None,
    camera: Camera,
    *,
    covariances: Tensor | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> Projected:
    """``project_gaussians(means, covariances_from(quats, scales), camera)``, compiled.

    CPU tensors only. ``covariances`` (N, 3, 3) replace quats/scales; they get no
    gradient, so they must not require one (the viewer's precomputed, frozen model;
    the full-covariance ablation trains through the torch projection instead).
    The result has no ``cov2d`` (the conics carry the footprint; nothing reads it).
    """
    if covariances is not None and covariances.requires_grad:
        raise ValueError("project_compiled gives no gradient to covariances; use project_gaussians")
    if covariances is None and (quats is None or scales is None):
        raise ValueError("project_compiled needs quats and scales, or covariances")
    if not torch.is_grad_enabled():  # no graph: the kernel then skips the backward's state
        means, quats, scales = (None if t is None else t.detach() for t in (means, quats, scales))
    means2d, conics, comp, depths, radii = CompiledProjection.apply(
        means, quats, scales, covariances, camera, float(near), float(far), float(eps2d)
    )
    return Projected(means2d=means2d, conics=conics, depths=depths, radii=radii, compensation=comp)
