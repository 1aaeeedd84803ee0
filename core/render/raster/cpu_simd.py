"""SIMD tile compositing on the CPU, forward and backward.

The kernel is ``core/kernels/native/composite_simd.c``.

The numba kernels of ``core.render.raster.cpu`` evaluate one pixel at a time; this
C kernel evaluates a 16-pixel tile row per vector (see that file). It is built with
the system C compiler at first use (``core.kernels.native_build``); without one, everything
keeps the numba kernels. Every decision (which pixels a Gaussian reaches, where a
pixel stops) is numba's; values differ by the polynomial exp's 2 float32 ulps, and
gradients by the backward's float32 running state (numba keeps float64; 3DGS's CUDA
kernel float32) — tested against numba and the reference.

It takes float32 composites on 16-px tiles (:func:`supports`): gradient-free frames
(viewer, evaluation renders) and training steps, where ``CpuComposite`` pairs its
forward with its backward.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from core.kernels import native_build
from core.kernels.pool import run_ranges, run_workers

__all__ = [
    "SOURCE", "TILE", "SimdComposite", "composite", "library", "status", "supports",
    "why_unavailable",
]  # fmt: skip

SOURCE = Path(native_build.__file__).with_name("native") / "composite_simd.c"
TILE = 16  # the kernel's vector width in pixels (one tile row)

_P = ctypes.c_void_p
_I = ctypes.c_int64
_COMMON = [_I, _I, _P, _P, _P, _P, _I, _P, _P, _I, _I, _I, _I, _P, _P, _P]
_SIGNATURES = {
    "culling_boxes": ([_I, _I, _P, _P, _P, _P, ctypes.c_float, _I, _I, _P, _P], None),
    "composite_simd": ([*_COMMON, _P, _P, _P], ctypes.c_int),
    "composite_simd_backward": ([*_COMMON, _P, _P, _P, _P, _I, _P], ctypes.c_int),
}


def library(extra_flags: tuple[str, ...] = (), source: Path = SOURCE) -> ctypes.CDLL | None:
    """The built kernel library (None where it cannot be built); ``extra_flags``
    build a variant, e.g. another vector width for the tests, ``source`` another
    version of the kernel (``bench.composite_ab``)."""
    lib = native_build.load(source, extra_flags)
    if lib is not None and lib.composite_simd.argtypes is None:
        _set_signatures(lib)
    return lib


def _set_signatures(lib: ctypes.CDLL) -> None:
    """Declare the kernels' C signatures (ctypes would otherwise guess int arguments)."""
    for name, (args, res) in _SIGNATURES.items():
        fn = getattr(lib, name)
        fn.argtypes = args
        fn.restype = res


def why_unavailable() -> str | None:
    """None when the SIMD kernel is built and loaded, otherwise why not."""
    return native_build.why_unavailable(SOURCE)


def status() -> dict[str, str]:
    """Which kernel float32 compositing runs here: the SIMD library's path, or numba
    and why (for ``glint info``)."""
    lib = library()
    if lib is None:
        return {"kernel": "numba", "why": why_unavailable() or "unknown"}
    return {"kernel": "simd", "library": str(lib._name)}


def supports(tensors: tuple[Tensor, ...], tile_size: int) -> bool:
    """float32 inputs, 16-px tiles and a built kernel."""
    if tile_size != TILE or any(t.dtype != torch.float32 for t in tensors):
        return False
    return library() is not None


def _check(name: str, arr: np.ndarray, dtype: type) -> None:
    if arr.dtype != dtype or not arr.flags.c_contiguous:
        raise ValueError(f"{name} must be C-contiguous {np.dtype(dtype).name}, got {arr.dtype}")


class SimdComposite:
    """One composite's inputs for the C kernels: the culling setup's arrays
    (``cpu._Setup.args()``) plus per-Gaussian pixel boxes and exp floors,
    computed once and shared by the forward and its backward."""

    def __init__(self, arrays: tuple, width: int, height: int, lib: ctypes.CDLL | None = None):
        self.lib = lib or library()
        if self.lib is None:
            raise RuntimeError(f"the SIMD compositing kernel is unavailable: {why_unavailable()}")
        (means2d, conics, opac, feats, ids, offsets, tiles_x, tile_size, _xs, _ys, consts,
         mode, geo) = arrays  # fmt: skip
        if tile_size != TILE:
            raise ValueError(f"the SIMD kernel needs {TILE}-px tiles, got {tile_size}")
        for name, arr in (("means2d", means2d), ("conics", conics), ("opacities", opac),
                          ("features", feats), ("consts", consts)):  # fmt: skip
            _check(name, arr, np.float32)
        for name, arr, dt in (("gauss_ids", ids, np.int64), ("offsets", offsets, np.int64),
                              ("mode", mode, np.int8), ("geo", geo, np.float64)):  # fmt: skip
            _check(name, arr, dt)
        if offsets.shape[0] - 1 != tiles_x * -(-height // TILE) or tiles_x != -(-width // TILE):
            raise ValueError(f"the tile lists do not cover a {width}x{height} image")
        self.width, self.height = width, height
        self.n, self.n_ch = opac.shape[0], feats.shape[1]
        self.box = np.empty((self.n, 4), np.int32)
        self.floors = np.empty(self.n, np.float32)
        self._keep = (means2d, conics, opac, feats, ids, offsets, consts, mode, geo)
        m2, op, md, ge, bx, fl = (a.ctypes.data for a in (means2d, opac, mode, geo, self.box,
                                                          self.floors))  # fmt: skip
        a_min = float(consts[2])

        def boxes(lo: int, hi: int) -> None:  # ctypes drops the GIL for each call
            self.lib.culling_boxes(lo, hi, m2, op, md, ge, a_min, width, height, bx, fl)

        run_ranges(boxes, self.n, ())
        self._common = (
            m2, conics.ctypes.data, op, feats.ctypes.data, self.n_ch, ids.ctypes.data,
            offsets.ctypes.data, offsets.shape[0] - 1, tiles_x, width, height, bx, fl,
            consts.ctypes.data,
        )  # fmt: skip

    def _run(self, kernel, n_workers: int, tail: tuple) -> None:
        status = [0] * n_workers

        def worker(w: int, nw: int) -> None:
            status[w] = kernel(w, nw, *self._common, *tail)

        run_workers(worker, n_workers, ())
        if any(status):
            raise MemoryError("the SIMD compositing kernel could not allocate its tile buffers")

    def forward(
        self,
        n_workers: int,
        out_feat: np.ndarray,
        out_T: np.ndarray,
        out_last: np.ndarray | None = None,
    ) -> None:
        """Fill ``out_feat`` (H, W, C), ``out_T`` (H, W, starting at 1) and, for a
        backward, ``out_last`` (H, W) int32."""
        shape = (self.height, self.width)
        for name, arr, dt, shp in (("out_feat", out_feat, np.float32, (*shape, self.n_ch)),
                                   ("out_T", out_T, np.float32, shape),
                                   ("out_last", out_last, np.int32, shape)):  # fmt: skip
            if arr is not None:
                _check(name, arr, dt)
                if arr.shape != shp:
                    raise ValueError(f"{name} must have shape {shp}, got {arr.shape}")
        last = out_last.ctypes.data if out_last is not None else None
        self._run(self.lib.composite_simd, n_workers,
                  (out_feat.ctypes.data, out_T.ctypes.data, last))  # fmt: skip

    def backward(
        self,
        n_workers: int,
        final_T: np.ndarray,
        last: np.ndarray,
        grad_feat: np.ndarray,
        grad_alpha: np.ndarray,
        gbuf: np.ndarray,
    ) -> None:
        """Add each worker's gradient sums into ``gbuf[w]``, a zeroed (n_workers, N,
        6 + C) float64 array: means2d (2), conic (3), opacity, features."""
        shape = (self.height, self.width)
        for name, arr, dt, shp in (("final_T", final_T, np.float32, shape),
                                   ("last", last, np.int32, shape),
                                   ("grad_feat", grad_feat, np.float32, (*shape, self.n_ch)),
                                   ("grad_alpha", grad_alpha, np.float32, shape),
                                   ("gbuf", gbuf, np.float64,
                                    (n_workers, self.n, 6 + self.n_ch))):  # fmt: skip
            _check(name, arr, dt)
            if arr.shape != shp:
                raise ValueError(f"{name} must have shape {shp}, got {arr.shape}")
        tail = tuple(a.ctypes.data for a in (final_T, last, grad_feat, grad_alpha))
        self._run(self.lib.composite_simd_backward, n_workers,
                  (*tail, self.n, gbuf.ctypes.data))  # fmt: skip


def composite(
    arrays: tuple,
    n_workers: int,
    out_feat: np.ndarray,
    out_T: np.ndarray,
    lib: ctypes.CDLL | None = None,
) -> None:
    """Gradient-free forward: fill ``out_feat`` (H, W, C) and ``out_T`` (H, W,
    starting at 1) from the culling setup ``arrays`` on ``n_workers`` threads
    (``lib``: a variant from :func:`library`; default the standard build)."""
    if out_feat.ndim != 3:
        raise ValueError(f"out_feat must be (H, W, C), got shape {out_feat.shape}")
    _check("out_feat", out_feat, np.float32)
    height, width, _ = out_feat.shape
    SimdComposite(arrays, width, height, lib).forward(n_workers, out_feat, out_T)
