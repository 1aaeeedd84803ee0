"""Where the compiled (numba, ``nogil``) kernels run: their thread count and pool.

Shared by the rasteriser, the fused projection and the compiled deferred shading, so
every kernel follows one setting (``core.threads.configure_cpu_threads``).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

__all__ = ["kernel_threads", "run_ranges", "run_workers", "set_kernel_threads"]

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
    """The configured kernel thread count (core.threads), else torch's intra-op count."""
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
