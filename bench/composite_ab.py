"""Two builds of the SIMD compositing kernel, timed against each other in one process.

    python -m bench.composite_ab --old a76acb9 [--new FILE] [--rounds 24] [--threads 2]

``--old`` and ``--new`` are git revisions or files of ``core/kernels/native/
composite_simd.c`` (``--new`` defaults to the working tree's). Both are built with the
project's flags and run on the same inputs: a 512² viewer frame of bench.viewer's
sphere of flat discs and of bench.raster's random blob (forward only, as a viewer frame
composites), and training-size composites (the blob at 128² with 20k and 70k Gaussians,
11 channels, the forward, and the backward timed on its own after an untimed forward:
the larger count's per-Gaussian arrays no longer fit the caches, as a trained object's
do not). Each round runs both builds in an order that
alternates from round to round, each twice, timing the second run: whichever build
runs first in a round meets colder caches (that alone read as ±10% here). Ratios are
the median of the rounds' own new/old ratios with their range, and the outputs of the
two builds are compared (largest absolute difference).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from bench.common import bench_camera, machine_line, random_gaussians
from core.kernels import native_build
from core.kernels.pool import kernel_threads
from core.kernels.threads import configure_cpu_threads
from core.render.gbuffer import gbuffer_features
from core.render.raster import PROJECTORS, bin_gaussians, covariances_from, cpu_simd
from core.render.raster.cpu import _Setup

ROOT = Path(__file__).resolve().parents[1]
SOURCE_PATH = "core/kernels/native/composite_simd.c"


def source_of(ref: str | None, into: Path) -> Path:
    """The kernel source of a file path, a git revision, or (None) the working tree."""
    if ref is None:
        return cpu_simd.SOURCE
    if Path(ref).is_file():
        return Path(ref)
    try:
        text = subprocess.run(
            ["git", "show", f"{ref}:{SOURCE_PATH}"], cwd=ROOT, check=True,
            capture_output=True, text=True,
        ).stdout  # fmt: skip
    except (subprocess.CalledProcessError, OSError) as exc:
        why = exc.stderr.strip() if isinstance(exc, subprocess.CalledProcessError) else exc
        raise SystemExit(f"--old/--new {ref!r}: neither a file nor a revision holding "
                         f"{SOURCE_PATH} ({why})") from exc  # fmt: skip
    path = into / f"composite_simd_{ref.replace('/', '_')}.c"
    path.write_text(text)
    return path


def build(source: Path):
    lib = cpu_simd.library(source=source)
    if lib is None:
        raise SystemExit(f"{source} did not build: {native_build.why_unavailable(source)}")
    return lib


def _composite_inputs(means, covs, opac, feats, cam) -> tuple[tuple, int, int, int]:
    proj = PROJECTORS["cpu"](means, None, None, cam, covariances=covs)
    op = (opac * proj.compensation).contiguous()
    w, h = cam.width, cam.height
    bins = bin_gaussians(proj.means2d, proj.depths, proj.radii, w, h)
    args = _Setup(proj.means2d, proj.conics, op, feats, bins, w, h, torch.float32).args()
    return args, w, h, feats.shape[1]


def viewer_sphere(n: int, size: int):
    from bench.deferred_frame import _sphere_scene

    s = _sphere_scene(n, size)
    feats = gbuffer_features(s["means"], s["colors"], s["normals"], s["w_r"], s["camera"])
    return _composite_inputs(s["means"], s["covariances"], s["opacities"],
                             feats.contiguous(), s["camera"])  # fmt: skip


def blob(n: int, size: int, channels: int):
    means, quats, scales, opac, _ = random_gaussians(n, channels=8)
    feats = torch.rand(n, channels, generator=torch.Generator().manual_seed(1))
    return _composite_inputs(means, covariances_from(quats, scales), opac, feats,
                             bench_camera(size))  # fmt: skip


Case = Callable[[], tuple[np.ndarray, float]]  # a run: its output and the ms it timed


def frame_case(lib, inputs) -> Case:
    args, w, h, c = inputs

    def run() -> tuple[np.ndarray, float]:
        out = np.zeros((h, w, c), np.float32)
        t0 = time.perf_counter()
        cpu_simd.composite(args, kernel_threads(), out, np.ones((h, w), np.float32), lib=lib)
        return out, 1e3 * (time.perf_counter() - t0)

    return run


def training_case(lib, inputs, part: str) -> Case:
    """Forward with last-contributor counts (part "fwd", timed) or that forward untimed
    and then its backward, timed alone (part "bwd": a difference of two timed runs went
    negative when the machine was busy)."""
    args, w, h, c = inputs
    rng = np.random.default_rng(3)
    g_feat = rng.standard_normal((h, w, c)).astype(np.float32)
    g_alpha = rng.standard_normal((h, w)).astype(np.float32)
    nw = kernel_threads()

    def run() -> tuple[np.ndarray, float]:
        out, T = np.zeros((h, w, c), np.float32), np.ones((h, w), np.float32)
        last = np.zeros((h, w), np.int32)
        t0 = time.perf_counter()  # the forward with its culling setup, as a step runs it
        k = cpu_simd.SimdComposite(args, w, h, lib)
        k.forward(nw, out, T, last)
        if part == "fwd":
            return out, 1e3 * (time.perf_counter() - t0)
        gbuf = np.zeros((nw, k.n, 6 + c))
        t0 = time.perf_counter()
        k.backward(nw, T, last, g_feat, g_alpha, gbuf)
        return gbuf.sum(0), 1e3 * (time.perf_counter() - t0)

    return run


def ab(cases: dict[str, Case], rounds: int) -> tuple[dict, dict]:
    """ms of "old" and "new" per round, order alternating, the second of two runs timed;
    and each build's last output."""
    times: dict[str, list[float]] = {k: [] for k in cases}
    outs: dict[str, np.ndarray] = {}
    names = list(cases)
    for r in range(rounds):
        for name in names if r % 2 else names[::-1]:
            outs[name] = cases[name]()[0]  # the warm run, whose output is compared
            times[name].append(cases[name]()[1])
    return times, outs


def summarise(label: str, times: dict, outs: dict) -> dict:
    old, new = times["old"], times["new"]
    ratios = [b / a for a, b in zip(old, new, strict=True)]
    scale = max(float(np.abs(outs["old"]).max()), 1e-30)
    return {
        "case": label,
        "old_ms": round(statistics.median(old), 3),
        "new_ms": round(statistics.median(new), 3),
        "new_over_old": round(statistics.median(ratios), 3),
        "range": [round(min(ratios), 3), round(max(ratios), 3)],
        "max_rel_diff": float(np.abs(outs["new"] - outs["old"]).max() / scale),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", required=True, help="git revision or file of the old source")
    ap.add_argument("--new", default=None, help="git revision or file (default: this tree's)")
    ap.add_argument("--rounds", type=int, default=24)
    ap.add_argument("--gaussians", type=int, default=100_000, help="of the 512² frames")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument(
        "--train-gaussians", type=int, nargs="+", default=[20_000, 70_000],
        help="Gaussian counts of the 128² training composites (bench.train_step's; a "
        "trained object's)",
    )  # fmt: skip
    ap.add_argument("--threads", type=int, default=None, help="kernel threads (default: all)")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args(argv)
    if args.rounds < 1:
        ap.error("--rounds must be at least 1")
    if min(args.train_gaussians) < 1:
        ap.error("--train-gaussians must be positive counts")
    configure_cpu_threads(args.threads)
    with tempfile.TemporaryDirectory(prefix="glint-ab-") as tmp:
        libs = {"old": build(source_of(args.old, Path(tmp))),
                "new": build(source_of(args.new, Path(tmp)))}  # fmt: skip
        rows = []
        for label, inputs in (
            (f"{args.size}² frame, viewer sphere", viewer_sphere(args.gaussians, args.size)),
            (f"{args.size}² frame, random blob", blob(args.gaussians, args.size, 8)),
        ):
            cases = {k: frame_case(lib, inputs) for k, lib in libs.items()}
            rows.append(summarise(label, *ab(cases, args.rounds)))
        for n in args.train_gaussians:
            train = blob(n, 128, 11)
            fwd_t, fwd_o = ab(
                {k: training_case(lib, train, "fwd") for k, lib in libs.items()}, args.rounds
            )
            bwd_t, bwd_o = ab(
                {k: training_case(lib, train, "bwd") for k, lib in libs.items()}, args.rounds
            )
            label = f"128² training composite, {n:,} Gaussians"
            rows.append(summarise(f"{label}, forward", fwd_t, fwd_o))
            rows.append(summarise(f"{label}, backward", bwd_t, bwd_o))
    print(f"{machine_line()}; {kernel_threads()} kernel threads; old {args.old}, "
          f"new {args.new or 'working tree'}; {args.rounds} rounds")  # fmt: skip
    print()
    print("| case | old ms | new ms | new/old [range] | max rel. diff |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['case']} | {r['old_ms']} | {r['new_ms']} | {r['new_over_old']} "
              f"[{r['range'][0]}–{r['range'][1]}] | {r['max_rel_diff']:.1e} |")  # fmt: skip
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
