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

import torch

from bench.common import interleaved_medians, machine_line
from core.losses import ssim, ssim_reference


def run(sizes: list[int], repeat: int) -> list[dict]:
    rows = []
    for size in sizes:
        g = torch.Generator().manual_seed(size)
        ref = torch.rand(size, size, 3, generator=g)
        img = (ref + 0.1 * torch.randn(size, size, 3, generator=g)).clamp(0, 1)
        img.requires_grad_(True)

        def fwd(f, img=img, ref=ref) -> None:
            with torch.no_grad():
                f(img, ref)

        def fwd_bwd(f, img=img, ref=ref) -> None:
            f(img, ref).backward()
            img.grad = None

        med = interleaved_medians(
            {
                "sf": lambda: fwd(ssim),
                "rf": lambda: fwd(ssim_reference),
                "sb": lambda: fwd_bwd(ssim),
                "rb": lambda: fwd_bwd(ssim_reference),
            },
            repeat,
        )
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
