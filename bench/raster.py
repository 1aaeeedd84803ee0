"""Rasteriser speed and peak memory: forward and forward+backward per backend.

    python -m bench.raster                 # the default cases, a Markdown table
    python -m bench.raster --backends reference cpu --sizes 128:20000
    python -m bench.raster --backends cpu --sizes 512:100000 --breakdown --threads 2
    python -m bench.raster --backends cpu --sizes 128:20000 --threads 2 --split-threads

Each case runs in its own process so peak RSS is that case's alone. ``--split-threads``
runs the way every ``glint`` command does (torch on one thread, the kernels on
``--threads``); without it torch and the kernels share ``--threads``. ``--breakdown``
adds a second table that splits a forward into projection, tile binning (shared by
all backends) and compositing, and times the compositing's forward+backward alone.
"""

from __future__ import annotations

import argparse
import json

import torch

from bench.common import (
    bench_camera,
    machine_line,
    median_time,
    peak_rss_mib,
    random_gaussians,
    run_isolated,
)
from core.kernels.pool import kernel_threads
from core.render.raster import (
    BACKENDS,
    PROJECTORS,
    bin_gaussians,
    covariances_from,
    project_gaussians,
    rasterize,
)

DEFAULT_SIZES = ["64:2000", "128:10000"]


def breakdown(case: dict, cam, means, quats, scales, opac, feats) -> dict:
    """Median ms of projection, binning and compositing (forward; and fwd+bwd)."""
    size, backend, repeat = case["size"], case["backend"], case.get("repeat", 5)
    composite = BACKENDS[backend][1]
    fused = PROJECTORS.get(backend)

    def project():
        if fused is not None:
            return fused(means, quats, scales, cam)
        return project_gaussians(means, covariances_from(quats, scales), cam)

    with torch.no_grad():
        t_proj = median_time(project, repeat=repeat)
        proj = project()
        t_bin = median_time(
            lambda: bin_gaussians(proj.means2d, proj.depths, proj.radii, size, size),
            repeat=repeat,
        )
        bins = bin_gaussians(proj.means2d, proj.depths, proj.radii, size, size)
        t_comp = median_time(lambda: composite(proj, opac, feats, bins, size, size), repeat=repeat)
    leaves = [t.detach().clone().requires_grad_(True) for t in (proj.means2d, proj.conics)]
    op, fe = (t.clone().requires_grad_(True) for t in (opac, feats))
    proj_g = type(proj)(leaves[0], leaves[1], proj.depths, proj.radii, proj.cov2d)

    def comp_fwd_bwd():
        f, a = composite(proj_g, op, fe, bins, size, size)
        (f.sum() + a.sum()).backward()

    t_comp_fb = (
        median_time(comp_fwd_bwd, repeat=repeat) if case.get("backward", True) else float("nan")
    )
    return {
        "projection_ms": t_proj * 1e3,
        "binning_ms": t_bin * 1e3,
        "composite_ms": t_comp * 1e3,
        "composite_fwd_bwd_ms": t_comp_fb * 1e3,
        "tile_pairs": int(bins.gauss_ids.numel()),
    }


def run_case(case: dict) -> dict:
    size, n, backend = case["size"], case["n"], case["backend"]
    channels = case.get("channels", 8)
    if case.get("split_threads"):
        from core.kernels.threads import configure_cpu_threads

        configure_cpu_threads(case.get("threads") or None)
    elif case.get("threads"):
        torch.set_num_threads(case["threads"])
    cam = bench_camera(size)
    means, quats, scales, opac, feats = random_gaussians(n, channels=channels)
    base_rss = peak_rss_mib()

    def fwd():
        with torch.no_grad():
            return rasterize(means, quats, scales, opac, feats, cam, backend=backend)

    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, feats)]

    def fwd_bwd():
        r = rasterize(*params[:4], params[4], cam, backend=backend)
        (r.features.sum() + r.alpha.sum()).backward()

    repeat = case.get("repeat", 5)
    t_f = median_time(fwd, repeat=repeat)
    t_fb = median_time(fwd_bwd, repeat=repeat) if case.get("backward", True) else float("nan")
    cover = float(fwd().alpha.mean())
    extra = breakdown(case, cam, means, quats, scales, opac, feats) if case.get("breakdown") else {}
    return {
        **case,
        **extra,
        "threads_used": torch.get_num_threads(),
        "kernel_threads_used": kernel_threads(),
        "forward_ms": t_f * 1e3,
        "forward_backward_ms": t_fb * 1e3,
        "peak_rss_mib": peak_rss_mib(),
        "rss_before_mib": base_rss,
        "mean_alpha": cover,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--backends", nargs="+", default=["reference"])
    ap.add_argument("--sizes", nargs="+", default=DEFAULT_SIZES, help="SIZE:N pairs")
    ap.add_argument("--channels", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--no-backward", action="store_true")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument(
        "--split-threads",
        action="store_true",
        help="Glint's process layout (core.kernels.threads): torch on one thread, the compiled "
        "kernels on --threads (default: every usable CPU)",
    )
    ap.add_argument(
        "--breakdown", action="store_true", help="also time projection/binning/compositing"
    )
    ap.add_argument("--case", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.case:
        print(json.dumps(run_case(json.loads(args.case))))
        return
    rows = []
    for spec in args.sizes:
        size, n = (int(x) for x in spec.split(":"))
        for backend in args.backends:
            case = {
                "size": size,
                "n": n,
                "backend": backend,
                "channels": args.channels,
                "repeat": args.repeat,
                "backward": not args.no_backward,
                "threads": args.threads,
                "split_threads": args.split_threads,
                "breakdown": args.breakdown,
            }
            rows.append(run_isolated("bench.raster", case))
    used = next((r for r in rows if "threads_used" in r), {})
    print(
        f"Machine: {machine_line()}; cases ran with {used.get('threads_used')} torch threads, "
        f"{used.get('kernel_threads_used')} kernel threads\n"
    )
    cols = ["backend", "image", "Gaussians", "channels", "forward ms", "fwd+bwd ms"]
    cols += ["peak RSS MiB", "RSS growth MiB", "mean alpha"]
    print("| " + " | ".join(cols) + " |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            head = f"| {r['backend']} | {r['size']}² | {r['n']} | {r['channels']}"
            print(f"{head} | error: {r['error']} | | | | |")
            continue
        print(
            f"| {r['backend']} | {r['size']}² | {r['n']} | {r['channels']} | {r['forward_ms']:.1f} "
            f"| {r['forward_backward_ms']:.1f} | {r['peak_rss_mib']:.0f} "
            f"| {r['peak_rss_mib'] - r['rss_before_mib']:.0f} | {r['mean_alpha']:.2f} |"
        )
    if args.breakdown:
        cols = ["backend", "image", "Gaussians", "tile pairs", "projection ms", "binning ms"]
        cols += ["composite fwd ms", "composite fwd+bwd ms"]
        print("\n| " + " | ".join(cols) + " |")
        print("|---|---|---|---|---|---|---|---|")
        for r in rows:
            if "error" in r:
                continue
            print(
                f"| {r['backend']} | {r['size']}² | {r['n']} | {r['tile_pairs']} "
                f"| {r['projection_ms']:.1f} | {r['binning_ms']:.1f} | {r['composite_ms']:.1f} "
                f"| {r['composite_fwd_bwd_ms']:.1f} |"
            )


if __name__ == "__main__":
    main()
