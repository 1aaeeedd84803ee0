"""L_multi (Eq. 12–14) per selected pixel in one compiled pass, with its backward (CPU).

The torch path lifts each selected reference pixel with its depth, projects it into the
neighbour, samples the neighbour's depth bilinearly, lifts that and projects it back:
about forty small ops on the selected pixels and their autograd, 2.1 ms of a 50 ms
multi-view step at 128² (docs/benchmarks.md). Here one loop does the round trip per
pixel and keeps what its backward needs; the backward walks the chain by hand (error →
back-projection into the reference → the neighbour's lifted point → its bilinear depth
and pixel position → the reference point → the reference depth). The neighbour's
depth gradient is a scatter into its bilinear taps, so each worker adds into its own
buffer. Same definition and guards as ``core.training.losses.multi_view_loss`` (the
pixel selection stays there); float64 inside (``tests/test_multi_view_compiled.py``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor
from torch.autograd.function import once_differentiable

from core.kernels.pool import kernel_threads, run_workers
from core.scene.cameras import Camera

__all__ = ["multi_view_loss_compiled"]

# per pixel state kept for the backward
_S_OK, _S_E, _S_UN, _S_VN, _S_DN = range(5)
_N_STATE = 5


@njit(nogil=True, cache=True, inline="always")
def _rot(R, x, y, z):  # pragma: no cover - numba
    """R v."""
    return (R[0, 0] * x + R[0, 1] * y + R[0, 2] * z,
            R[1, 0] * x + R[1, 1] * y + R[1, 2] * z,
            R[2, 0] * x + R[2, 1] * y + R[2, 2] * z)  # fmt: skip


@njit(nogil=True, cache=True, inline="always")
def _rot_t(R, x, y, z):  # pragma: no cover - numba
    """Rᵀ v."""
    return (R[0, 0] * x + R[1, 0] * y + R[2, 0] * z,
            R[0, 1] * x + R[1, 1] * y + R[2, 1] * z,
            R[0, 2] * x + R[1, 2] * y + R[2, 2] * z)  # fmt: skip


@njit(nogil=True, cache=True, inline="always")
def _to_cam(R, t, x, y, z):  # pragma: no cover - numba
    """R p + t."""
    a, b, c = _rot(R, x, y, z)
    return a + t[0], b + t[1], c + t[2]


@njit(nogil=True, cache=True, inline="always")
def _to_world(R, t, x, y, z):  # pragma: no cover - numba
    """Rᵀ (p − t)."""
    return _rot_t(R, x - t[0], y - t[1], z - t[2])


@njit(nogil=True, cache=True, inline="always")
def _in_front(x, y, z):  # pragma: no cover - numba
    """``project_in_front``'s test: finite and z > 1e-4 |p|."""
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return False
    return z > 1e-4 * math.sqrt(x * x + y * y + z * z)


@njit(nogil=True, cache=True, inline="always")
def _tap_box(h, w, u, v):  # pragma: no cover - numba
    """Where ``bilinear_lookup`` reads an (h, w) image at pixel coordinates (u, v):
    (finite, inside, x0, y0, x1, y1, fx, fy); the far taps (x1, y1) stay in the image
    for a 1-px wide or high one."""
    x, y = u - 0.5, v - 0.5
    if not (math.isfinite(x) and math.isfinite(y)):
        return False, False, 0, 0, 0, 0, 0.0, 0.0
    inside = x >= 0.0 and y >= 0.0 and x <= w - 1 and y <= h - 1
    x0 = int(min(max(math.floor(x), 0.0), max(w - 2, 0)))
    y0 = int(min(max(math.floor(y), 0.0), max(h - 2, 0)))
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    fx = min(max(x - x0, 0.0), 1.0)
    fy = min(max(y - y0, 0.0), 1.0)
    return True, inside, x0, y0, x1, y1, fx, fy


@njit(nogil=True, cache=True, inline="always")
def _taps(img, u, v):  # pragma: no cover - numba
    """``bilinear_lookup`` at pixel coordinates (u, v): (value, inside, x0, y0, x1, y1,
    fx, fy)."""
    finite, inside, x0, y0, x1, y1, fx, fy = _tap_box(img.shape[0], img.shape[1], u, v)
    if not finite:
        return 0.0, False, 0, 0, 0, 0, 0.0, 0.0
    v00, v01 = np.float64(img[y0, x0]), np.float64(img[y0, x1])
    v10, v11 = np.float64(img[y1, x0]), np.float64(img[y1, x1])
    val = (v00 * (1 - fx) + v01 * fx) * (1 - fy) + (v10 * (1 - fx) + v11 * fx) * fy
    return val, inside, x0, y0, x1, y1, fx, fy


@njit(nogil=True, cache=True, inline="always")
def _into_neighbour(p, d_ref, Rr, tr, kr, Rn, tn, kn):  # pragma: no cover - numba
    """Reference pixel p (flat index) lifted with its depth and projected into the
    neighbour (Eq. 12–13): (in front, u_r, v_r, u_n, v_n, z_n)."""
    w = d_ref.shape[1]
    fxr, fyr, cxr, cyr = kr[0], kr[1], kr[2], kr[3]
    fxn, fyn, cxn, cyn = kn[0], kn[1], kn[2], kn[3]
    ur, vr = (p % w) + 0.5, (p // w) + 0.5
    dr = np.float64(d_ref[p // w, p % w])
    X, Y, Z = _to_world(Rr, tr, (ur - cxr) / fxr * dr, (vr - cyr) / fyr * dr, dr)
    cx, cy, cz = _to_cam(Rn, tn, X, Y, Z)
    if not _in_front(cx, cy, cz):
        return False, ur, vr, 0.0, 0.0, cz
    return True, ur, vr, fxn * cx / cz + cxn, fyn * cy / cz + cyn, cz


@njit(nogil=True, cache=True)
def _footprint(idx, d_ref, Rr, tr, kr, Rn, tn, kn, out):  # pragma: no cover - numba
    """Mark in ``out`` (the neighbour's H, W) every pixel :func:`_forward` reads for the
    pixels ``idx``: the bilinear taps of each projection that lands inside and in front
    (elsewhere the round trip is dropped whatever the neighbour holds)."""
    h, w = out.shape
    for m in range(idx.shape[0]):
        front, _, _, un, vn, cz = _into_neighbour(idx[m], d_ref, Rr, tr, kr, Rn, tn, kn)
        if not (front and cz > 0.0):
            continue
        finite, inside, x0, y0, x1, y1, _, _ = _tap_box(h, w, un, vn)
        if finite and inside:
            out[y0, x0] = True
            out[y0, x1] = True
            out[y1, x0] = True
            out[y1, x1] = True


@njit(nogil=True, cache=True)
def _forward(idx, d_ref, d_nb, v_nb, Rr, tr, kr, Rn, tn, kn, max_err, state):  # pragma: no cover
    """Round trip of every selected pixel: ``state`` rows (ok, error, u_n, v_n, d_n);
    returns (sum of errors, sum of exp(−error)·error, kept)."""
    fxr, fyr, cxr, cyr = kr[0], kr[1], kr[2], kr[3]
    fxn, fyn, cxn, cyn = kn[0], kn[1], kn[2], kn[3]
    total, total_w, kept = 0.0, 0.0, 0
    for m in range(idx.shape[0]):
        state[m, _S_OK] = 0.0
        front, ur, vr, un, vn, cz = _into_neighbour(idx[m], d_ref, Rr, tr, kr, Rn, tn, kn)
        if not front:
            continue
        dn, inside, _, _, _, _, _, _ = _taps(d_nb, un, vn)
        ok_v, _, _, _, _, _, _, _ = _taps(v_nb, un, vn)
        if not (inside and cz > 0.0 and ok_v > 0.999 and dn > 0.0):
            continue
        X2, Y2, Z2 = _to_world(Rn, tn, (un - cxn) / fxn * dn, (vn - cyn) / fyn * dn, dn)
        bx, by, bz = _to_cam(Rr, tr, X2, Y2, Z2)
        if not (_in_front(bx, by, bz) and bz > 0.0):
            continue
        ub, vb = fxr * bx / bz + cxr, fyr * by / bz + cyr
        e = math.sqrt((ub - ur) ** 2 + (vb - vr) ** 2 + 1e-12)
        if not (math.isfinite(e) and e <= max_err):
            continue
        state[m, _S_OK] = 1.0
        state[m, _S_E] = e
        state[m, _S_UN], state[m, _S_VN], state[m, _S_DN] = un, vn, dn
        total += e
        total_w += math.exp(-e) * e
        kept += 1
    return total, total_w, kept


@njit(nogil=True, cache=True)
def _backward_part(
    w_id, n_workers, idx, d_ref, d_nb, Rr, tr, kr, Rn, tn, kn, state, scale, weighted,
    g_ref, g_nb,
):  # fmt: skip  # pragma: no cover - numba
    """Worker ``w_id``'s share of the kept pixels: the reference depth's gradient (one
    pixel each, no sharing) and the neighbour's into ``g_nb[w_id]``."""
    n = idx.shape[0]
    step = (n + n_workers - 1) // n_workers
    w = d_ref.shape[1]
    fxr, fyr, cxr, cyr = kr[0], kr[1], kr[2], kr[3]
    fxn, fyn, cxn, cyn = kn[0], kn[1], kn[2], kn[3]
    gn = g_nb[w_id]
    for m in range(w_id * step, min((w_id + 1) * step, n)):
        if state[m, _S_OK] == 0.0:
            continue
        p = idx[m]
        ur, vr = (p % w) + 0.5, (p // w) + 0.5
        dr = np.float64(d_ref[p // w, p % w])
        e = state[m, _S_E]
        un, vn, dn = state[m, _S_UN], state[m, _S_VN], state[m, _S_DN]
        g_e = scale * (math.exp(-e) if weighted else 1.0)
        # forward quantities again
        rxn, ryn = (un - cxn) / fxn, (vn - cyn) / fyn
        X2, Y2, Z2 = _to_world(Rn, tn, rxn * dn, ryn * dn, dn)
        bx, by, bz = _to_cam(Rr, tr, X2, Y2, Z2)
        ub, vb = fxr * bx / bz + cxr, fyr * by / bz + cyr
        # e = |uv_back − uv_r|
        gub, gvb = g_e * (ub - ur) / e, g_e * (vb - vr) / e
        # uv_back = proj_ref(b)
        gbx, gby = gub * fxr / bz, gvb * fyr / bz
        gbz = -(gub * fxr * bx + gvb * fyr * by) / (bz * bz)
        # b = Rr P2 + tr: g_P2 = Rrᵀ g_b
        gX2, gY2, gZ2 = _rot_t(Rr, gbx, gby, gbz)
        # P2 = Rnᵀ (q − tn): g_q = Rn g_P2
        gqx, gqy, gqz = _rot(Rn, gX2, gY2, gZ2)
        g_un = gqx * dn / fxn
        g_vn = gqy * dn / fyn
        g_dn = gqx * rxn + gqy * ryn + gqz
        # d_n = bilinear(d_nb, u_n, v_n)
        _, _, x0, y0, x1, y1, fx, fy = _taps(d_nb, un, vn)
        v00, v01 = np.float64(d_nb[y0, x0]), np.float64(d_nb[y0, x1])
        v10, v11 = np.float64(d_nb[y1, x0]), np.float64(d_nb[y1, x1])
        gn[y0, x0] += g_dn * (1 - fx) * (1 - fy)
        gn[y0, x1] += g_dn * fx * (1 - fy)
        gn[y1, x0] += g_dn * (1 - fx) * fy
        gn[y1, x1] += g_dn * fx * fy
        g_un += g_dn * ((v01 - v00) * (1 - fy) + (v11 - v10) * fy)
        g_vn += g_dn * ((v10 * (1 - fx) + v11 * fx) - (v00 * (1 - fx) + v01 * fx))
        # uv_n = proj_nb(c), c = Rn P + tn
        X, Y, Z = _to_world(Rr, tr, (ur - cxr) / fxr * dr, (vr - cyr) / fyr * dr, dr)
        cx, cy, cz = _to_cam(Rn, tn, X, Y, Z)
        gcx, gcy = g_un * fxn / cz, g_vn * fyn / cz
        gcz = -(g_un * fxn * cx + g_vn * fyn * cy) / (cz * cz)
        gX, gY, gZ = _rot_t(Rn, gcx, gcy, gcz)
        # P = Rrᵀ (d r_r − tr): g_d = (Rr g_P) · r_r
        gqx, gqy, gqz = _rot(Rr, gX, gY, gZ)
        g_ref[p // w, p % w] = gqx * (ur - cxr) / fxr + gqy * (vr - cyr) / fyr + gqz


def _cam(c: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    i = c.intrinsics
    R = c.R.detach().to(torch.float64).contiguous().numpy()
    t = c.t.detach().to(torch.float64).reshape(3).contiguous().numpy()
    return R, t, np.array([i.fx, i.fy, i.cx, i.cy], np.float64)


class _MultiView(torch.autograd.Function):
    """The loss value computed by ``_forward``, with the hand-written backward."""

    @staticmethod
    def forward(ctx, d_ref, d_nb, value, meta):  # type: ignore[override]
        ctx.meta = (*meta, d_ref.dtype, d_nb.dtype)
        return d_ref.new_tensor(value)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        a_ref, a_nb, ids, cams, state, kept, weighted, dt_ref, dt_nb = ctx.meta
        g_ref = np.zeros(a_ref.shape)
        nw = max(1, min(kernel_threads(), ids.shape[0]))
        g_nb = np.zeros((nw, *a_nb.shape))
        if kept:
            args = (ids, a_ref, a_nb, *cams[0], *cams[1], state, float(grad) / kept,
                    bool(weighted), g_ref, g_nb)  # fmt: skip
            run_workers(_backward_part, nw, args)
        g_nb_t = torch.from_numpy(g_nb.sum(0)).to(dt_nb)
        return torch.from_numpy(g_ref).to(dt_ref), g_nb_t, None, None


def neighbour_footprint(depth_ref: Tensor, idx: Tensor, cam_ref: Camera, cam_nb: Camera) -> Tensor:
    """(H, W) bool of the neighbour view: the pixels whose depth and validity
    :func:`multi_view_loss_compiled` reads for the reference pixels ``idx``, by the same
    arithmetic (a neighbour rendered at these pixels only gives the same loss and
    gradients as a whole one)."""
    out = np.zeros((cam_nb.height, cam_nb.width), np.bool_)
    ids = idx.to(torch.int64).contiguous().numpy()
    a_ref = depth_ref.detach().contiguous().numpy()
    _footprint(ids, a_ref, *_cam(cam_ref), *_cam(cam_nb), out)
    return torch.from_numpy(out)


def multi_view_loss_compiled(
    depth_ref: Tensor,
    depth_nb: Tensor,
    idx: Tensor,
    valid_nb: Tensor,
    cam_ref: Camera,
    cam_nb: Camera,
    max_error_px: float,
    error_weighting: bool,
) -> tuple[Tensor, int]:
    """(loss, kept) of the round trip of the reference pixels ``idx`` (flat indices,
    CPU); 0 with zero gradients when none is kept. Differentiable in both depths."""
    cams = (_cam(cam_ref), _cam(cam_nb))
    a_ref = depth_ref.detach().contiguous().numpy()
    a_nb = depth_nb.detach().contiguous().numpy()
    ids = idx.to(torch.int64).contiguous().numpy()
    v_nb = valid_nb.detach().to(depth_nb.dtype).contiguous().numpy()
    state = np.zeros((ids.shape[0], _N_STATE))
    total, total_w, kept = _forward(ids, a_ref, a_nb, v_nb, *cams[0], *cams[1],
                                    float(max_error_px), state)  # fmt: skip
    value = (total_w if error_weighting else total) / kept if kept else 0.0
    meta = (a_ref, a_nb, ids, cams, state, kept, error_weighting)
    return _MultiView.apply(depth_ref, depth_nb, value, meta), int(kept)
