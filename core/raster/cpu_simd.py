"""SIMD compositing for gradient-free CPU frames (viewer, evaluation renders).

The numba forward of ``core.raster.cpu_backend`` evaluates one pixel at a time; a
viewer frame needs no gradient, so it can take ``native/composite_simd.c``, which
evaluates a 16-pixel tile row per instruction stream (see that file). It is built
with the system C compiler at first use (``core.native_build``); without one,
frames keep the numba kernel. Results match the numba kernel up to its polynomial
exp (about 2 float32 ulps) — tested against it and the reference.

It applies when no input wants a gradient, everything is float32 and tiles are 16 px.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from core import native_build
from core.kernel_pool import run_ranges, run_workers

__all__ = ["SOURCE", "applies", "composite", "library", "why_unavailable"]

SOURCE = Path(__file__).with_name("native") / "composite_simd.c"
TILE = 16  # the kernel's vector width in pixels (one tile row)

_P = ctypes.c_void_p
_I = ctypes.c_int64
_COMPOSITE_ARGS = [_I, _I, _P, _P, _P, _P, _I, _P, _P, _I, _I, _I, _I, _P, _P, _P, _P, _P]
_BOXES_ARGS = [_I, _I, _P, _P, _P, _P, ctypes.c_float, _I, _I, _P, _P]


def library(extra_flags: tuple[str, ...] = ()) -> ctypes.CDLL | None:
    """The built kernel library (None where it cannot be built); ``extra_flags``
    build a variant, e.g. another vector width for the tests."""
    lib = native_build.load(SOURCE, extra_flags)
    if lib is not None and lib.composite_simd.argtypes is None:
        _set_signatures(lib)
    return lib


def _set_signatures(lib: ctypes.CDLL) -> None:
    """Declare the kernel's C signatures (ctypes would otherwise guess int arguments)."""
    lib.composite_simd.argtypes = _COMPOSITE_ARGS
    lib.composite_simd.restype = ctypes.c_int
    lib.culling_boxes.argtypes = _BOXES_ARGS
    lib.culling_boxes.restype = None


def why_unavailable() -> str | None:
    """None when the SIMD kernel is built and loaded, otherwise why not."""
    return native_build.why_unavailable(SOURCE)


def applies(
    means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, tile_size: int
) -> bool:
    """Whether this composite can take the SIMD kernel (see the module docstring)."""
    tensors = (means2d, conics, opacities, features)
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return False
    if tile_size != TILE or any(t.dtype != torch.float32 for t in tensors):
        return False
    return library() is not None


def composite(
    arrays: tuple,
    n_workers: int,
    out_feat: np.ndarray,
    out_T: np.ndarray,
    lib: ctypes.CDLL | None = None,
) -> None:
    """Fill ``out_feat`` (H, W, C) and ``out_T`` (H, W, starting at 1) from the
    culling setup ``arrays`` (``cpu_backend._Setup.args()``), on ``n_workers`` threads
    (``lib``: a variant from :func:`library`; default the standard build)."""
    lib = lib or library()
    if lib is None:
        raise RuntimeError(f"the SIMD compositing kernel is unavailable: {why_unavailable()}")
    (means2d, conics, opac, feats, ids, offsets, tiles_x, tile_size, _xs, _ys, consts,
     mode, geo) = arrays  # fmt: skip
    if tile_size != TILE:
        raise ValueError(f"the SIMD kernel needs {TILE}-px tiles, got {tile_size}")
    for name, arr in (("means2d", means2d), ("conics", conics), ("opacities", opac),
                      ("features", feats), ("consts", consts), ("out_feat", out_feat),
                      ("out_T", out_T)):  # fmt: skip
        if arr.dtype != np.float32 or not arr.flags.c_contiguous:
            raise ValueError(f"{name} must be C-contiguous float32, got {arr.dtype}")
    height, width, n_ch = out_feat.shape
    box = np.empty((opac.shape[0], 4), np.int32)
    floors = np.empty(opac.shape[0], np.float32)
    m2, op, md, ge, bx, fl = (a.ctypes.data for a in (means2d, opac, mode, geo, box, floors))
    a_min = float(consts[2])

    def boxes(lo: int, hi: int) -> None:  # ctypes drops the GIL for each call
        lib.culling_boxes(lo, hi, m2, op, md, ge, a_min, width, height, bx, fl)

    run_ranges(boxes, opac.shape[0], ())
    ptr = [a.ctypes.data for a in (conics, opac, feats, ids, offsets, consts, out_feat, out_T)]
    status = [0] * n_workers

    def worker(w: int, nw: int) -> None:
        status[w] = lib.composite_simd(w, nw, m2, ptr[0], ptr[1], ptr[2], n_ch, ptr[3], ptr[4],
                                       offsets.shape[0] - 1, tiles_x, width, height, bx, fl, ptr[5],
                                       ptr[6], ptr[7])  # fmt: skip

    run_workers(worker, n_workers, ())
    if any(status):
        raise MemoryError("the SIMD compositing kernel could not allocate its tile buffer")
