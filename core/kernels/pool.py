"""Where the compiled (numba, ``nogil``) kernels run: their thread count and pool.

Shared by the rasteriser, the fused projection and the compiled deferred shading, so
every kernel follows one setting (``core.kernels.threads.configure_cpu_threads``).
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import numpy as np
import torch

__all__ = [
    "BufferPool", "kernel_threads", "run_ranges", "run_workers", "scratch_zeros",
    "set_kernel_threads", "store_dtype", "zeros_touched",
]  # fmt: skip

_POOL: ThreadPoolExecutor | None = None
_POOL_KEY: tuple[int, int] = (0, 0)  # (pid, size): a forked child builds its own pool
_POOL_LOCK = threading.Lock()


def run_workers(kernel: Callable[..., None], n_workers: int, args: tuple) -> None:
    """Run ``kernel(w, n_workers, *args)`` for w in 0..n_workers-1, concurrently.

    The kernels are compiled with ``nogil=True`` and run on plain threads: worker 0
    on the calling thread, the others on a small persistent pool. (A numba
    ``prange`` wrapper does the same job but added 2-7 s of compile time per kernel
    and dtype, and brings a second OpenMP thread pool next to torch's.)
    """
    global _POOL, _POOL_KEY
    if n_workers == 1:
        kernel(0, 1, *args)
        return
    with _POOL_LOCK:
        pid = os.getpid()
        if _POOL is None or _POOL_KEY[0] != pid or _POOL_KEY[1] < n_workers - 1:
            if _POOL is not None and _POOL_KEY[0] == pid:
                _POOL.shutdown(wait=False)
            _POOL = ThreadPoolExecutor(n_workers - 1, thread_name_prefix="glint-raster")
            _POOL_KEY = (pid, n_workers - 1)
        futures = [_POOL.submit(kernel, w, n_workers, *args) for w in range(1, n_workers)]
    kernel(0, n_workers, *args)
    for f in futures:
        f.result()


_KERNEL_THREADS: int | None = None


def set_kernel_threads(n: int | None) -> None:
    """Threads for the compiled kernels; None: follow ``torch.get_num_threads()``."""
    global _KERNEL_THREADS
    if n is not None and n < 1:
        raise ValueError(f"kernel threads must be >= 1, got {n}")
    _KERNEL_THREADS = n


def kernel_threads() -> int:
    """The configured kernel thread count (core.kernels.threads), else torch's intra-op count."""
    return _KERNEL_THREADS or max(1, torch.get_num_threads())


def run_ranges(kernel: Callable[..., None], n: int, args: tuple) -> None:
    """``kernel(lo, hi, *args)`` over contiguous slices of range(n), one per kernel thread.

    For per-item kernels (per Gaussian, per pixel row) whose items cost about the same.
    """
    workers = kernel_threads()
    step = -(-n // workers) if n else 0
    ranges = [(lo, min(lo + step, n)) for lo in range(0, n, step)] if n else []
    if len(ranges) <= 1:
        for lo, hi in ranges:
            kernel(lo, hi, *args)
        return

    def by_worker(w: int, n_workers: int, *a: object) -> None:
        for lo, hi in ranges[w::n_workers]:
            kernel(lo, hi, *a)

    run_workers(by_worker, len(ranges), args)


def store_dtype(dtype: torch.dtype | None) -> type:
    """The numpy dtype a kernel writes a torch dtype's values in: float32 for float32
    (the kernel rounds its float64 arithmetic on store, as a conversion afterwards
    would, and the pass over the array is saved), float64 for anything else (converted
    after by the caller)."""
    return np.float32 if dtype == torch.float32 else np.float64


def zeros_touched(shape: tuple[int, ...], dtype: type) -> np.ndarray:
    """A zeroed array whose pages are faulted in here, on the calling thread.

    ``np.zeros`` of a large array maps untouched pages, so the kernel threads that
    first write them take the page faults, concurrently; those serialise on the
    process's memory map and made a backward kernel's time vary 7-25 ms (measured:
    a (2, 20000, 14) float64 gradient buffer). Filling it first keeps them at 7-8 ms.
    """
    out = np.empty(shape, dtype)
    out.fill(0)
    return out


class BufferPool:
    """Idle flat work buffers kept for reuse, so a buffer's pages stay mapped.

    A fresh large array pays a page fault on every page it touches (about 2 ms per
    MiB on the development VM); a reused one only what the caller does with it.
    ``take`` hands out the smallest idle buffer of the dtype that holds ``size``
    elements (or a new one); ``give`` returns it, and only the ``keep`` largest
    idle buffers stay. Concurrent takers get different buffers.
    """

    def __init__(self, keep: int) -> None:
        self.keep = keep
        self.idle: list[np.ndarray] = []
        self._lock = threading.Lock()

    def take(self, size: int, dtype: type | np.dtype) -> np.ndarray:
        """A flat buffer of at least ``size`` elements (contents undefined)."""
        dt = np.dtype(dtype)
        with self._lock:
            fits = [i for i, b in enumerate(self.idle) if b.dtype == dt and b.size >= size]
            if fits:
                return self.idle.pop(min(fits, key=lambda i: self.idle[i].size))
        return np.empty(size, dt)

    def give(self, buf: np.ndarray) -> None:
        with self._lock:
            self.idle.append(buf)
            self.idle.sort(key=lambda b: b.size, reverse=True)
            del self.idle[self.keep :]  # keep the largest


# The per-thread gradient sums of a backward pass: one in use at a time, at most two.
_SCRATCH = BufferPool(keep=2)


@contextmanager
def scratch_zeros(shape: tuple[int, ...], dtype: type = np.float64) -> Iterator[np.ndarray]:
    """A zeroed work buffer from a small per-process pool, back in the pool afterwards.

    For the per-thread gradient sums of a backward pass, (threads, N, 6 + C) float64,
    72 MiB at 300k Gaussians: a fresh array every step pays the page faults of
    mapping it again, a pooled one only a memset. Nothing may keep a view of it after
    the ``with`` block; concurrent callers get different buffers.
    """
    size = math.prod(shape)
    buf = _SCRATCH.take(size, dtype)
    view = buf[:size].reshape(shape)
    view.fill(0)
    try:
        yield view
    finally:
        _SCRATCH.give(buf)
