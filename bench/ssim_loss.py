"""The SSIM term of the RGB loss (Eq. 15): separable vs plain 2D window, side by side.

    python -m bench.ssim_loss [--sizes 128 256 512 800] [--threads 1] [--repeat 15]

Every training step evaluates ``rgb_loss``, whose D-SSIM blurs five local moments
with 3DGS's 11×11 Gaussian window. ``core.evaluation.ssim.ssim`` does it with one grouped,
separable convolution; ``ssim_reference`` is the plain definition (five 2D
convolutions). Both run in the same process, alternately, on the same images,
forward only and forward + backward (gradient for the rendered image). ``--threads``
defaults to 1: Glint keeps torch on one thread (``core.kernels.threads``).
"""

from __future__ import annotations

import argparse

import torch

from bench.common import fast_vs_plain, fast_vs_plain_table
from core.evaluation.ssim import ssim, ssim_reference


def run(sizes: list[int], repeat: int) -> list[dict]:
    rows = []
    for size in sizes:
        g = torch.Generator().manual_seed(size)
        ref = torch.rand(size, size, 3, generator=g)
        img = (ref + 0.1 * torch.randn(size, size, 3, generator=g)).clamp(0, 1)
        img.requires_grad_(True)
        med = fast_vs_plain(
            lambda img=img, ref=ref: ssim(img, ref),
            lambda img=img, ref=ref: ssim_reference(img, ref),
            (img,),
            None,
            repeat,
        )
        rows.append({"size": size, "label": f"{size}²", **med})
    return rows


def format_table(rows: list[dict]) -> str:
    return fast_vs_plain_table(rows, "image", ("separable", "2D window"))


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
