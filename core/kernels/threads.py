"""CPU thread layout of a Glint process: torch's own ops on one thread, the compiled
rasteriser kernels on every usable core.

Why: torch's OpenMP workers spin while they wait for the next op, and a training
step is hundreds of small ops between the compiled kernels, whose own threads then
compete with the spinners. On a 2-core machine, two processes side by side (a worker
and the API's viewer, or two workers) each took 2.6-3.0 s per multi-view training
step with 2 torch threads and 165-171 ms with this layout; alone, one process takes
142-144 ms vs 150 ms (128 px, 20k Gaussians, ``python -m bench.train_step --device
cpu --size 128 --n 20000 --envmap 32 --threads 2 [--split-threads]``). The kernels'
pool threads block instead of spinning, so the layout degrades gracefully under load.
"""

from __future__ import annotations

import os

ENV_VAR = "GLINT_KERNEL_THREADS"


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask, e.g. a container's cpuset)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def kernel_threads_from_env() -> int | None:
    """``GLINT_KERNEL_THREADS`` as a positive int, None when unset; raises on garbage."""
    raw = os.environ.get(ENV_VAR, "").strip()
    if not raw:
        return None
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"{ENV_VAR} must be a positive integer, got {raw!r}")
    return n


def configure_cpu_threads(kernel_threads: int | None = None) -> int:
    """Apply the layout: torch on one thread, the kernels on ``kernel_threads`` (default:
    ``GLINT_KERNEL_THREADS``, else every usable CPU), and freed memory kept in the
    process (core.kernels.allocator). Returns the kernel thread count."""
    import torch

    from core.kernels.allocator import keep_freed_memory
    from core.kernels.pool import set_kernel_threads

    keep_freed_memory()
    n = kernel_threads or kernel_threads_from_env() or usable_cpus()
    torch.set_num_threads(1)
    set_kernel_threads(n)
    return n
