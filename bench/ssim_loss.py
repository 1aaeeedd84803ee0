"""The SSIM term of the RGB loss (Eq. 15): separable vs plain 2D window, side by side.

    python -m bench.ssim_loss [--sizes 128 256 512 800] [--threads 1] [--repeat 15]

Every training step evaluates ``rgb_loss``, whose D-SSIM blurs five local moments
with 3DGS's 11×11 Gaussian window. ``core.losses.ssim`` does it with one grouped,
separable convolution; ``ssim_reference`` is the plain definition (five 2D
convolutions). Both run in the same process, alternately, on the same images,
forward only and forward + backward (gradient for the rendered image). ``--threads``
defaults to 1: Glint keeps torch on one thread (``core.threads``).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from bench.common import machine_line
from core.losses import ssim, ssim_reference


def run(sizes: list[int], repeat: int) -> list[dict]:
    rows = []
    for size in sizes:
        g = torch.Generator().manual_seed(size)
        ref = torch.rand(size, size, 3, generator=g)
        img = (ref + 0.1 * torch.randn(size, size, 3, generator=g)).clamp(0, 1)
        img.requires_grad_(True)

        def fwd(f=ssim):
            with torch.no_grad():
                f(img, ref)

        def fwd_bwd(f=ssim):
            f(img, ref).backward()
            img.grad = None

        times: dict[str, list[float]] = {k: [] for k in ("sf", "rf", "sb", "rb")}
        for _ in range(2):  # warm-up
            fwd(), fwd(ssim_reference), fwd_bwd(), fwd_bwd(ssim_reference)
        for _ in range(repeat):  # interleaved, so drift hits both alike
            for key, fn in (
                ("sf", fwd),
                ("rf", lambda: fwd(ssim_reference)),
                ("sb", fwd_bwd),
                ("rb", lambda: fwd_bwd(ssim_reference)),
            ):
                t0 = time.perf_counter()
                fn()
                times[key].append(time.perf_counter() - t0)
        med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
        rows.append({"size": size, **med})
    return rows


def format_table(rows: list[dict]) -> str:
    lines = [
        f"Machine: {machine_line()}",
        "",
        "| image | forward: separable | 2D window | ratio | fwd+bwd: separable | 2D window "
        "| ratio |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['size']}² | {r['sf']:.2f} ms | {r['rf']:.2f} ms | {r['rf'] / r['sf']:.2f}× "
            f"| {r['sb']:.2f} ms | {r['rb']:.2f} ms | {r['rb'] / r['sb']:.2f}× |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512, 800])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=15)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    print(format_table(run(args.sizes, args.repeat)))


if __name__ == "__main__":
    main()
