"""Rasteriser speed and peak memory: forward and forward+backward per backend.

    python -m bench.raster                 # the default cases, a Markdown table
    python -m bench.raster --backends reference cpu --sizes 128:20000

Each case runs in its own process so peak RSS is that case's alone.
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
from core.raster import rasterize

DEFAULT_SIZES = ["64:2000", "128:10000"]


def run_case(case: dict) -> dict:
    size, n, backend = case["size"], case["n"], case["backend"]
    channels = case.get("channels", 8)
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
    return {
        **case,
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
            }
            rows.append(run_isolated("bench.raster", case))
    print(f"Machine: {machine_line()}\n")
    cols = ["backend", "image", "Gaussians", "channels", "forward ms", "fwd+bwd ms"]
    cols += ["peak RSS MiB", "mean alpha"]
    print("| " + " | ".join(cols) + " |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            head = f"| {r['backend']} | {r['size']}² | {r['n']} | {r['channels']}"
            print(f"{head} | error: {r['error']} | | | |")
            continue
        print(
            f"| {r['backend']} | {r['size']}² | {r['n']} | {r['channels']} | {r['forward_ms']:.1f} "
            f"| {r['forward_backward_ms']:.1f} | {r['peak_rss_mib']:.0f} | {r['mean_alpha']:.2f} |"
        )


if __name__ == "__main__":
    main()
