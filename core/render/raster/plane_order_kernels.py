"""The numba kernels of per-pixel plane order (``core.render.raster.plane_order``):
pixel-major per 16-px tile, each pixel's contributors gathered from the tile list,
insertion-sorted by where its ray meets each splat's plane, composited front to back;
the backward walks the forward's kept runs (or rebuilt ones) back to front.

Kept apart from the autograd function, the plane keys and the torch reference they are
tested against (``tests/test_plane_order.py``), so each file has one job.
"""

from __future__ import annotations

import math

import numpy as np

from core.render.raster.cpu import _entry_rows, _row_span

try:
    from numba import njit
except ImportError:  # pragma: no cover - numba is a declared dependency

    def njit(*_args, **_kwargs):  # type: ignore[no-redef]
        return lambda fn: fn


# Early termination (:func:`_fill_sorted`): a saturated pixel's run is walked again after
# this many insertions, and the tile's stop is looked for every this many list entries.
# Walks cost a run's length each; 16 rather than 4 took a dense disc sphere's gather from
# 213 to 185 ms and a trained teapot view's from 23 to 22 ms (32: no better); exact
# either way.
_WALK_EVERY = 16
_TILE_CHECK_EVERY = 32
# A tile's runs first get 64 entries a pixel; a tile that needs more grows the arrays to
# twice its largest run a pixel, up to this many entries (16 bytes each), or to its count.
_MAX_GROWN_ROOM = 1 << 22


@njit(nogil=True, fastmath=False, cache=True)
def _count_candidates(
    lo, hi, x0, x1, y0, y1, tile_size, means2d, gauss_ids, mode, geo, begin
):  # fmt: skip  # pragma: no cover - numba
    """``begin[p]``: where pixel p's run starts, room for every entry whose culling
    ellipse covers the pixel (a superset of its contributors: no exp() here); returns
    the room needed in all."""
    npix = tile_size * tile_size
    begin[:] = 0
    for i in range(lo, hi):
        g = gauss_ids[i]
        m, geo_g, mxd, myd, r0, r1 = _entry_rows(g, mode, geo, means2d, x0, x1, y0, y1)
        if r0 >= r1:
            continue
        for py in range(r0, r1):
            q0, q1 = _row_span(m, geo_g, mxd, py + 0.5 - myd, x0, x1)
            for px in range(q0, q1):
                begin[(py - y0) * tile_size + (px - x0) + 1] += 1
    for p in range(npix):
        begin[p + 1] += begin[p]
    return begin[npix]


@njit(nogil=True, fastmath=False, cache=True)
def _fill_sorted(
    lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys, consts,
    mode, geo, planes, rx, ry, begin, end, cand_i, cand_key, cand_g, cand_s, cand_a, nxt,
    stop_key, t_all, since, reach_min, need,
):  # fmt: skip  # pragma: no cover - numba
    """Each pixel p's contributors (alpha ≥ 1/255), sorted by plane depth (stable:
    entries arrive in tile order and ties keep it), as slots ``cand_s[begin[p]:end[p]]``
    (keys in ``cand_key``). A slot s holds the contributor's place in the tile list
    ``cand_i[s]`` (entry ``lo + k`` holds Gaussian ``gauss_ids[lo + k]``), its Gaussian
    factor exp(power) ``cand_g[s]`` and its alpha ``cand_a[s]``, written once: the
    insertion sort shifts only keys and slots (a trained model's view shifts about ten
    entries an insertion, its splats of one surface arriving in no particular order),
    and the walks and the compositing read alpha without looking up the opacity. Slots
    are taken in order from ``nxt[p]`` and not reused when a walk drops entries.
    Gaussian-major over the entries with the compiled backend's culling ellipses (a
    culling only: every visited pixel is tested with the reference formula). Insertion
    sort: the centre order is close to the plane order, so a heap (tried) was 2.6×
    slower on the bench scene.

    Early termination, exact: once a pixel's sorted run saturates (the compositing
    would stop at an entry with key ``stop_key[p]``), an entry whose key is not below
    that lands behind it and is never composited, so it is not inserted (nor its
    exp() taken where even its nearest possible key, z - h, is not below); the entries
    behind the stop are dropped. The run is walked again (:func:`_saturate`) after
    every ``_WALK_EVERY`` insertions, and first once the product of all its (1 - alpha),
    which does not depend on the order, falls below T_MIN. The tile stops early where
    every pixel has saturated in front of the nearest plane any later entry can
    have (``reach_min``: suffix minima of z - h).

    A pixel that ``need`` (H, W; empty: every pixel) leaves out starts stopped at -inf:
    its run stays empty and costs one comparison an entry, and the tile's stop no longer
    waits for it (the needed pixels' runs are exactly what they would be).

    Returns False, leaving the runs unfinished, where a pixel's slots outgrow its room
    (``begin[p + 1] - begin[p]``): with rooms from :func:`_count_candidates` (every
    insertion is a candidate) they cannot."""
    half, one, a_min, a_max, t_min = consts[0], consts[1], consts[2], consts[3], consts[4]
    npix = tile_size * tile_size
    inf = np.inf
    for p in range(npix):
        end[p] = begin[p]
        nxt[p] = begin[p]
        stop_key[p] = inf
        t_all[p] = 1.0
        since[p] = 0
    if need.shape[0] > 0:
        for py in range(y0, y1):
            for px in range(x0, x1):
                if not need[py, px]:
                    stop_key[(py - y0) * tile_size + (px - x0)] = -inf
    n = hi - lo
    lowest = inf
    for k in range(n - 1, -1, -1):
        g = gauss_ids[lo + k]
        zlo = planes[g, 4] - planes[g, 5]
        if zlo < lowest:
            lowest = zlo
        reach_min[k] = lowest
    tile_stop = inf
    for i in range(lo, hi):
        if (i - lo) % _TILE_CHECK_EVERY == 0 and i > lo:
            tile_stop = -inf
            for py in range(y0, y1):
                for px in range(x0, x1):
                    k_p = stop_key[(py - y0) * tile_size + (px - x0)]
                    if k_p > tile_stop:
                        tile_stop = k_p
        if reach_min[i - lo] >= tile_stop:
            break
        g = gauss_ids[i]
        m, geo_g, mxd, myd, r0, r1 = _entry_rows(g, mode, geo, means2d, x0, x1, y0, y1)
        if r0 >= r1:
            continue
        mx, my = means2d[g, 0], means2d[g, 1]
        a, b, c, o = conics[g, 0], conics[g, 1], conics[g, 2], opac[g]
        nx, ny, nz, d = planes[g, 0], planes[g, 1], planes[g, 2], planes[g, 3]
        z, h = planes[g, 4], planes[g, 5]
        zlo = z - h
        for py in range(r0, r1):
            q0, q1 = _row_span(m, geo_g, mxd, py + 0.5 - myd, x0, x1)
            dy = ys[py] - my
            ny_ry = ny * ry[py - y0] + nz
            for px in range(q0, q1):
                p = (py - y0) * tile_size + (px - x0)
                if zlo >= stop_key[p]:
                    continue
                dx = xs[px] - mx
                power = -half * (a * dx * dx + c * dy * dy) - b * dx * dy
                if not (power <= 0):
                    continue
                G = math.exp(power)
                alpha = o * G
                if alpha > a_max:
                    alpha = a_max
                if not (alpha >= a_min):
                    continue
                key = d / (nx * rx[px - x0] + ny_ry)
                if not math.isfinite(key):
                    key = z
                key = min(max(key, zlo), z + h)
                if key >= stop_key[p]:
                    continue
                slot = nxt[p]
                if slot >= begin[p + 1]:
                    return False
                nxt[p] = slot + 1
                cand_i[slot] = i - lo
                cand_g[slot] = G
                a_st = o * cand_g[slot]  # as the compositing computes it, in opac's dtype
                if a_st > a_max:
                    a_st = a_max
                cand_a[slot] = a_st
                j = end[p]
                s0 = begin[p]
                while j > s0 and cand_key[j - 1] > key:
                    cand_key[j] = cand_key[j - 1]
                    cand_s[j] = cand_s[j - 1]
                    j -= 1
                cand_key[j] = key
                cand_s[j] = slot
                end[p] += 1
                since[p] += 1
                t_all[p] *= 1.0 - np.float64(alpha)
                if since[p] >= _WALK_EVERY or (t_all[p] < t_min and stop_key[p] == inf):
                    since[p] = 0
                    if t_all[p] < t_min:
                        stop_key[p] = _saturate(
                            begin[p], end, p, cand_key, cand_s, cand_a, one, t_min
                        )
    return True


@njit(nogil=True, fastmath=False, cache=True)
def _saturate(s0, end, p, cand_key, cand_s, cand_a, one, t_min):  # pragma: no cover - numba
    """Walk pixel p's sorted run front to back as the compositing does; where it stops
    (the entry that takes the transmittance below T_MIN) drop what lies behind and
    return that entry's key, else +inf."""
    T = one
    for j in range(s0, end[p]):
        test_T = T * (one - cand_a[cand_s[j]])
        if test_T < t_min:
            end[p] = j + 1
            return cand_key[j]
        T = test_T
    return np.inf


@njit(nogil=True, fastmath=False, cache=True)
def _tile_runs(
    lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys, consts,
    mode, geo, planes, intr, begin, end, cand_i, cand_key, cand_g, cand_s, cand_a, nxt, rx, ry,
    stop_key, t_all, since, reach_min, need,
):  # fmt: skip  # pragma: no cover - numba
    """The tile's per-pixel contributor runs in plane order (:func:`_fill_sorted`);
    returns the candidate arrays and the suffix-minimum buffer (grown where needed).

    Each pixel first gets an equal share of the candidate arrays; only a tile where a
    run outgrows its share pays for the counting pass (exact rooms from the culling
    ellipses) and a second fill, and the arrays grow to twice what it needed, so the
    next tiles' shares fit (most tiles of a trained model: no counting pass at all)."""
    for px in range(x0, x1):
        rx[px - x0] = (np.float64(xs[px]) - intr[2]) / intr[0]
    for py in range(y0, y1):
        ry[py - y0] = (np.float64(ys[py]) - intr[3]) / intr[1]
    if hi - lo > reach_min.shape[0]:
        reach_min = np.empty(2 * (hi - lo), np.float64)
    npix = tile_size * tile_size
    share = cand_i.shape[0] // npix
    for p in range(npix + 1):
        begin[p] = p * share
    if _fill_sorted(
        lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys, consts,
        mode, geo, planes, rx, ry, begin, end, cand_i, cand_key, cand_g, cand_s, cand_a, nxt,
        stop_key, t_all, since, reach_min, need,
    ):  # fmt: skip
        return cand_i, cand_key, cand_g, cand_s, cand_a, reach_min
    total = _count_candidates(
        lo, hi, x0, x1, y0, y1, tile_size, means2d, gauss_ids, mode, geo, begin
    )
    most = 0
    for p in range(npix):
        most = max(most, begin[p + 1] - begin[p])
    want = max(total, min(2 * most * npix, _MAX_GROWN_ROOM))
    if want > cand_i.shape[0]:
        cand_i = np.empty(want, np.int32)
        cand_key = np.empty(want, np.float64)
        cand_g = np.empty(want, cand_g.dtype)
        cand_s = np.empty(want, np.int32)
        cand_a = np.empty(want, cand_a.dtype)
    _fill_sorted(
        lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys, consts,
        mode, geo, planes, rx, ry, begin, end, cand_i, cand_key, cand_g, cand_s, cand_a, nxt,
        stop_key, t_all, since, reach_min, need,
    )  # fmt: skip
    return cand_i, cand_key, cand_g, cand_s, cand_a, reach_min


@njit(nogil=True, fastmath=False, cache=True)
def _scratch(tile_size, opac):  # pragma: no cover - numba
    """A worker's buffers: run bounds, room for 64 contributors a pixel (keys, slots and
    the slots' place, exp(power) and alpha; grown per tile where needed), the next free
    slot a pixel, the tile's ray slopes, the early termination's per-pixel state and
    the tile list's suffix minima (grown where needed)."""
    npix = tile_size * tile_size
    return (
        np.zeros(npix + 1, np.int64),
        np.zeros(npix, np.int64),
        np.empty(64 * npix, np.int32),
        np.empty(64 * npix, np.float64),
        np.empty(64 * npix, opac.dtype),
        np.empty(64 * npix, np.int32),
        np.empty(64 * npix, opac.dtype),
        np.zeros(npix, np.int64),
        np.empty(tile_size, np.float64),
        np.empty(tile_size, np.float64),
        np.empty(npix, np.float64),
        np.empty(npix, np.float64),
        np.empty(npix, np.int32),
        np.empty(1024, np.float64),
    )


@njit(nogil=True, fastmath=False, cache=True)
def _tile_needed(need, x0, x1, y0, y1):  # pragma: no cover - numba
    """Whether ``need`` (H, W; empty: every pixel) asks for any pixel of the box."""
    if need.shape[0] == 0:
        return True
    for py in range(y0, y1):
        for px in range(x0, x1):
            if need[py, px]:
                return True
    return False


@njit(nogil=True, fastmath=False, cache=True, inline="always")
def _tile_box(t, tiles_x, tile_size, width, height):  # pragma: no cover - numba
    """Pixel bounds x0, y0, x1, y1 (exclusive) of tile t."""
    x0 = (t % tiles_x) * tile_size
    y0 = (t // tiles_x) * tile_size
    return x0, y0, min(x0 + tile_size, width), min(y0 + tile_size, height)


@njit(nogil=True, fastmath=False, cache=True)
def _forward_worker(
    w, n_workers, means2d, conics, opac, feats, gauss_ids, offsets, tiles_x, tile_size,
    xs, ys, consts, mode, geo, planes, intr, out_feat, out_T, out_last,
    run_g, run_G, run_T, run_at, tile_kept, need,
):  # fmt: skip  # pragma: no cover - numba
    """Tiles w, w + n_workers, ...: each pixel's contributors in plane order, composited
    front to back (out_T starts at 1, the others at 0); ``out_last`` counts the
    contributors composited. Where ``run_g`` has room (``run_g.shape[0] // n_tiles``
    entries a tile) the composited runs are kept for the backward: pixel (y, x)'s
    places in the tile list, exp(power) and transmittance in front of each at
    ``run_at[y, x]`` on, and ``tile_kept[t] = 1``. Pixels ``need`` (H, W; empty:
    all) leaves out come back empty (a loss reads a few pixels of this view)."""
    height, width, n_ch = out_feat.shape
    n_tiles = offsets.shape[0] - 1
    one, t_min = consts[1], consts[4]
    room = run_g.shape[0] // max(n_tiles, 1)
    (
        begin, end, cand_i, cand_key, cand_g, cand_s, cand_a, nxt, rx, ry, stop_key, t_all, since,
        reach_min,
    ) = _scratch(tile_size, opac)  # fmt: skip
    for t in range(w, n_tiles, n_workers):
        lo, hi = offsets[t], offsets[t + 1]
        if hi == lo:
            continue
        x0, y0, x1, y1 = _tile_box(t, tiles_x, tile_size, width, height)
        if not _tile_needed(need, x0, x1, y0, y1):
            continue
        cand_i, cand_key, cand_g, cand_s, cand_a, reach_min = _tile_runs(
            lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys,
            consts, mode, geo, planes, intr, begin, end, cand_i, cand_key, cand_g, cand_s, cand_a,
            nxt, rx, ry, stop_key, t_all, since, reach_min, need,
        )  # fmt: skip
        kept = room > 0
        at = t * room
        stop = at + room
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = (py - y0) * tile_size + (px - x0)
                if room > 0:
                    run_at[py, px] = at
                T = one
                m_used = 0
                for j in range(begin[p], end[p]):
                    slot = cand_s[j]
                    k = cand_i[slot]
                    G = cand_g[slot]
                    alpha = cand_a[slot]
                    test_T = T * (one - alpha)
                    if test_T < t_min:
                        break
                    wgt = alpha * T
                    g = gauss_ids[lo + k]
                    for ch in range(n_ch):
                        out_feat[py, px, ch] += feats[g, ch] * wgt
                    if kept:
                        if at < stop:
                            run_g[at] = k
                            run_G[at] = G
                            run_T[at] = T
                            at += 1
                        else:
                            kept = False
                    T = test_T
                    m_used += 1
                out_T[py, px] = T
                out_last[py, px] = m_used
        tile_kept[t] = 1 if kept else 0


@njit(nogil=True, fastmath=False, cache=True, inline="always")
def _contribution_backward(
    k, G, T_before, R, ga_T, px, py, tdat, xs, ys, a_max, grad_feat, acc,
):  # fmt: skip  # pragma: no cover - numba
    """One contributor's gradients (place k in the tile list, its Gaussian's data in
    ``tdat[k]``), back to front (the compiled backend's formulas), added into ``acc[k]``,
    given the transmittance in front of it; returns the colour behind it. The
    transmittance comes from the forward rather than from dividing back from the
    final one: that division chained each contributor to the next (a pixel-major
    walk has nothing else to overlap it with) and was most of the backward's time."""
    n_ch = tdat.shape[1] - 6
    raw = tdat[k, 5] * G
    alpha = a_max if raw > a_max else raw
    al = np.float64(alpha)
    one_m = 1.0 - al
    wgt = al * T_before
    gf = 0.0
    for ch in range(n_ch):
        gc = np.float64(grad_feat[py, px, ch])
        gf += gc * np.float64(tdat[k, 6 + ch])
        acc[k, 6 + ch] += wgt * gc
    d_alpha = T_before * gf + (ga_T - R) / one_m
    R += wgt * gf
    if raw > a_max:
        return R  # clamped: alpha depends on neither o nor the footprint
    d_pow = al * d_alpha
    dxd = np.float64(xs[px] - tdat[k, 0])
    dyd = np.float64(ys[py] - tdat[k, 1])
    ad, bd, cd = np.float64(tdat[k, 2]), np.float64(tdat[k, 3]), np.float64(tdat[k, 4])
    acc[k, 0] += (ad * dxd + bd * dyd) * d_pow
    acc[k, 1] += (cd * dyd + bd * dxd) * d_pow
    acc[k, 2] -= 0.5 * dxd * dxd * d_pow
    acc[k, 3] -= dxd * dyd * d_pow
    acc[k, 4] -= 0.5 * dyd * dyd * d_pow
    acc[k, 5] += np.float64(G) * d_alpha
    return R


@njit(nogil=True, fastmath=False, cache=True)
def _gather_entries(lo, hi, gauss_ids, means2d, conics, opac, feats, tdat):  # pragma: no cover
    """Row k of ``tdat``: tile entry lo + k's centre, conic, opacity and features, so
    the backward's pixel-major walk reads one compact block (in cache) instead of
    the whole model at random."""
    n_ch = feats.shape[1]
    for k in range(hi - lo):
        g = gauss_ids[lo + k]
        tdat[k, 0] = means2d[g, 0]
        tdat[k, 1] = means2d[g, 1]
        tdat[k, 2] = conics[g, 0]
        tdat[k, 3] = conics[g, 1]
        tdat[k, 4] = conics[g, 2]
        tdat[k, 5] = opac[g]
        for ch in range(n_ch):
            tdat[k, 6 + ch] = feats[g, ch]


@njit(nogil=True, fastmath=False, cache=True)
def _backward_worker(
    w, n_workers, means2d, conics, opac, feats, gauss_ids, offsets, tiles_x, tile_size,
    xs, ys, consts, mode, geo, planes, intr, final_T, last, run_g, run_G, run_T, run_at,
    tile_kept, grad_feat, grad_alpha, gbuf, need,
):  # fmt: skip  # pragma: no cover - numba
    """Each pixel's contributors in the forward's order, back to front: the forward's
    kept runs, or (a tile it had no room for) the runs rebuilt, their transmittances
    recomputed front to back as the forward did. A tile's gradients are summed per
    entry of its list first (``acc``: a few thousand rows, in cache, where scattering
    each contribution into gbuf[w, gaussian] missed it half the backward's time), then
    added into gbuf once an entry. Only the pixels in ``need`` (H, W: those with a
    non-zero upstream gradient; the others' contributions are all zero) are walked, and
    a tile rebuilds the runs of those pixels only, or nothing where it has none: the
    multi-view term reads a few thousand of a neighbour view's pixels."""
    height, width, _ = grad_feat.shape
    n_tiles = offsets.shape[0] - 1
    one, a_max = consts[1], consts[3]
    (
        begin, end, cand_i, cand_key, cand_g, cand_s, cand_a, nxt, rx, ry, stop_key, t_all, since,
        reach_min,
    ) = _scratch(tile_size, opac)  # fmt: skip
    n_q = 6 + feats.shape[1]
    acc = np.empty((1024, n_q), np.float64)
    tdat = np.empty((1024, n_q), feats.dtype)
    for t in range(w, n_tiles, n_workers):
        lo, hi = offsets[t], offsets[t + 1]
        if hi == lo:
            continue
        x0, y0, x1, y1 = _tile_box(t, tiles_x, tile_size, width, height)
        if not _tile_needed(need, x0, x1, y0, y1):
            continue
        if hi - lo > acc.shape[0]:
            acc = np.empty((2 * (hi - lo), n_q), np.float64)
            tdat = np.empty((2 * (hi - lo), n_q), feats.dtype)
        acc[: hi - lo] = 0.0
        _gather_entries(lo, hi, gauss_ids, means2d, conics, opac, feats, tdat)
        kept = tile_kept[t] == 1
        if not kept:
            cand_i, cand_key, cand_g, cand_s, cand_a, reach_min = _tile_runs(
                lo, hi, x0, x1, y0, y1, tile_size, means2d, conics, opac, gauss_ids, xs, ys,
                consts, mode, geo, planes, intr, begin, end, cand_i, cand_key, cand_g, cand_s,
                cand_a, nxt, rx, ry, stop_key, t_all, since, reach_min, need,
            )  # fmt: skip
        for py in range(y0, y1):
            for px in range(x0, x1):
                m_used = last[py, px]
                if m_used == 0 or not need[py, px]:
                    continue
                ga_T = np.float64(grad_alpha[py, px]) * np.float64(final_T[py, px])
                R = 0.0
                if kept:
                    at = run_at[py, px]
                    for j in range(at + m_used - 1, at - 1, -1):
                        k = run_g[j]
                        R = _contribution_backward(
                            k, run_G[j], np.float64(run_T[j]), R, ga_T, px, py, tdat, xs, ys,
                            a_max, grad_feat, acc,
                        )  # fmt: skip
                    continue
                p = (py - y0) * tile_size + (px - x0)
                s0 = begin[p]
                T = one  # the sort keys are spent: their places take the transmittances
                for j in range(s0, s0 + m_used):
                    cand_key[j] = T
                    T = T * (one - cand_a[cand_s[j]])
                for j in range(s0 + m_used - 1, s0 - 1, -1):
                    slot = cand_s[j]
                    R = _contribution_backward(
                        cand_i[slot], cand_g[slot], cand_key[j], R, ga_T, px, py, tdat, xs, ys,
                        a_max, grad_feat, acc,
                    )  # fmt: skip
        for k in range(hi - lo):
            g = gauss_ids[lo + k]
            for q in range(n_q):
                gbuf[w, g, q] += acc[k, q]
