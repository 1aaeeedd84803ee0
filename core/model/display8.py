"""Linear light → display-ready 8-bit sRGB, by table, bit-exact to the torch formula.

Every viewer frame and saved render ends here: the IEC 61966-2-1 curve (a ``pow`` per
value), rounding and a cast, ten image-sized torch ops, 3.3 ms of a 54 ms 512² viewer
frame. The 8-bit output only changes at 255 thresholds, and a float32's top 16 bits
(its exponent and 8 mantissa bits) pick a bucket narrow enough to hold at most one of
them anywhere in [0, 1]. So per value: a shift, a table read, one comparison. The
thresholds are found by bisection on the reference formula itself over float32 bit
patterns, so the table reproduces it everywhere but within 1 ulp of a step, where
torch's ``pow`` rounds differently in its vector body and scalar tail and the formula
gives either level depending on where a value sits in the tensor
(``tests/test_display8.py``).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch
from numba import njit
from torch import Tensor

from core.kernels.pool import run_ranges
from core.scene.imageio import linear_to_srgb

__all__ = ["encode_reference", "encode_srgb8"]

_SHIFT = 16
_ONE_BITS = 0x3F800000  # float32 1.0


def encode_reference(linear: Tensor) -> Tensor:
    """The formula: clamp to [0, 1], sRGB-encode, ×255, round half up, as uint8."""
    srgb = linear_to_srgb(linear.detach().float().clamp(0, 1))
    return (srgb * 255.0 + 0.5).clamp(0, 255).to(torch.uint8)


def _bits_to_float(bits: Tensor) -> Tensor:
    return bits.to(torch.int32).view(torch.float32)


@lru_cache(maxsize=1)
def tables() -> tuple[np.ndarray, np.ndarray]:
    """(base, threshold) per bucket of float32 bits >> 16 over [0, 1]: a value x of the
    bucket encodes to ``base + (x >= threshold)`` (threshold +inf: no step inside)."""
    # smallest float32 in [0, 1] that encodes to >= k, for k = 1..255 (bisection on bits)
    k = torch.arange(1, 256, dtype=torch.int64)
    lo = torch.zeros(255, dtype=torch.int64)  # encodes below k
    hi = torch.full((255,), _ONE_BITS, dtype=torch.int64)  # encodes to >= k
    while bool((hi - lo > 1).any()):
        mid = (lo + hi) // 2
        ok = encode_reference(_bits_to_float(mid)).to(torch.int64) >= k
        hi = torch.where(ok, mid, hi)
        lo = torch.where(ok, lo, mid)
    thresholds = hi
    n_buckets = (_ONE_BITS >> _SHIFT) + 1
    starts = torch.arange(n_buckets, dtype=torch.int64) << _SHIFT
    base = encode_reference(_bits_to_float(starts)).numpy().copy()
    thr = np.full(n_buckets, np.inf, np.float32)
    owner = (thresholds >> _SHIFT).numpy()
    if len(np.unique(owner)) != len(owner):
        raise RuntimeError("two sRGB thresholds share a bucket: the table would be inexact")
    starts_np = starts.numpy()
    for t_bits, b in zip(thresholds.numpy(), owner, strict=True):
        if t_bits > starts_np[b]:  # a threshold on the bucket start is in base already
            thr[b] = _bits_to_float(torch.tensor(t_bits)).item()
    return base, thr


@njit(nogil=True, cache=True)
def _encode_range(lo, hi, x, bits, base, thr, out):  # pragma: no cover - numba
    for i in range(lo, hi):
        v = x[i]
        if not v > 0.0:  # zero, negative, NaN
            out[i] = 0
        elif v >= 1.0:
            out[i] = 255
        else:
            b = bits[i] >> 16
            out[i] = base[b] + (1 if v >= thr[b] else 0)


def encode_srgb8(linear: Tensor) -> np.ndarray:
    """(..., C) linear values as uint8 sRGB on the CPU, as :func:`encode_reference`
    (see the top for the 1-ulp exception; a NaN gives 0)."""
    x = linear.detach().to(device="cpu", dtype=torch.float32).contiguous().numpy()
    flat = x.reshape(-1)
    out = np.empty(flat.shape[0], np.uint8)
    base, thr = tables()
    run_ranges(_encode_range, flat.shape[0], (flat, flat.view(np.int32), base, thr, out))
    return out.reshape(x.shape)
