"""Shared benchmark helpers: random scenes, timing, peak memory per case."""

from __future__ import annotations

import json
import platform
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from datetime import date

import torch

from core.scene.cameras import Camera, Intrinsics


def random_gaussians(n: int, seed: int = 0, device: str = "cpu", channels: int = 8):
    """A blob of n Gaussians in front of a camera at distance 3, roughly image-filling."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 0.45
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.03 + 0.005
    scales[:, 2] *= 0.05  # flat, as PGSR-DR drives them
    opac = torch.rand(n, generator=g) * 0.8 + 0.1
    feats = torch.rand(n, channels, generator=g)
    return [t.to(device) for t in (means, quats, scales, opac, feats)]


def bench_camera(size: int) -> Camera:
    intr = Intrinsics.from_fov_x(0.69, size, size)
    return Camera.look_at([0.0, -3.0, 0.5], [0, 0, 0], [0, 0, 1], intr)


def median_time(fn: Callable[[], object], warmup: int = 1, repeat: int = 5, sync=None) -> float:
    """Median wall time in seconds over ``repeat`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        fn()
    return statistics.median(interleaved_times({"case": fn}, repeat, sync)["case"]) / 1e3


def interleaved_times(
    cases: dict[str, Callable[[], object]], rounds: int, sync: Callable[[], None] | None = None
) -> dict[str, list[float]]:
    """ms of each case in each round; every round runs every case once, in order, so
    machine drift hits all alike (``sync``: wait for the device around each timing)."""
    times: dict[str, list[float]] = {k: [] for k in cases}
    for _ in range(rounds):
        for key, fn in cases.items():
            if sync:
                sync()
            t0 = time.perf_counter()
            fn()
            if sync:
                sync()
            times[key].append(1e3 * (time.perf_counter() - t0))
    return times


def interleaved_medians(
    cases: dict[str, Callable[[], object]], repeat: int, warmup: int = 2
) -> dict[str, float]:
    """Median ms of each case, timed in alternation so machine drift hits all alike."""
    for _ in range(warmup):
        for fn in cases.values():
            fn()
    return {k: statistics.median(v) for k, v in interleaved_times(cases, repeat).items()}


def fast_vs_plain(
    fast: Callable[[], torch.Tensor],
    plain: Callable[[], torch.Tensor],
    params: tuple[torch.Tensor, ...],
    weight: torch.Tensor | None,
    repeat: int,
) -> dict[str, float]:
    """Median ms of a fast path and its plain definition, forward (no autograd) and
    forward + backward (``weight`` the output's gradient; None for a scalar), alternated.

    Keys: ``ff``/``pf`` forward fast/plain, ``fb``/``pb`` forward+backward.
    """

    def fwd(f: Callable[[], torch.Tensor]) -> None:
        with torch.no_grad():
            f()

    def fwd_bwd(f: Callable[[], torch.Tensor]) -> None:
        f().backward(weight)
        for p in params:
            p.grad = None

    return interleaved_medians(
        {
            "ff": lambda: fwd(fast),
            "pf": lambda: fwd(plain),
            "fb": lambda: fwd_bwd(fast),
            "pb": lambda: fwd_bwd(plain),
        },
        repeat,
    )


def fast_vs_plain_table(rows: list[dict], size_header: str, names: tuple[str, str]) -> str:
    """Markdown table of :func:`fast_vs_plain` rows (each with a ``label``)."""
    fast, plain = names
    lines = [
        f"Machine: {machine_line()}",
        "",
        f"| {size_header} | forward: {fast} | {plain} | ratio | fwd+bwd: {fast} | {plain} "
        "| ratio |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['ff']:.2f} ms | {r['pf']:.2f} ms | {r['pf'] / r['ff']:.2f}× "
            f"| {r['fb']:.2f} ms | {r['pb']:.2f} ms | {r['pb'] / r['fb']:.2f}× |"
        )
    return "\n".join(lines)


def run_isolated(module: str, case: dict) -> dict:
    """Run one case in a fresh interpreter so its peak RSS is its own."""
    proc = subprocess.run(
        [sys.executable, "-m", module, "--case", json.dumps(case)],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        return {**case, "error": proc.stderr.strip().splitlines()[-1] if proc.stderr else "failed"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def machine_line() -> str:
    return (
        f"{platform.machine()}, {torch.get_num_threads()} torch threads, "
        f"torch {torch.__version__}, {date.today().isoformat()}"
    )
