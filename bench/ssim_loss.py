"""The SSIM term of the RGB loss (Eq. 15): the compiled blur against the torch paths.

    python -m bench.ssim_loss [--sizes 128 256 512 800] [--threads 1] [--repeat 15]
    python -m bench.ssim_loss --plain window     # the torch separable path vs 2D windows

Every training step evaluates ``rgb_loss``, whose D-SSIM blurs five local moments
with 3DGS's 11×11 Gaussian window. On the CPU ``core.evaluation.ssim.ssim`` blurs
with the compiled separable kernel (core.evaluation.ssim_compiled); ``--plain
separable`` (the default) times it against the torch path of the same function (one
grouped, separable convolution, what the GPU runs), ``--plain window`` times that
torch path against ``ssim_reference`` (five 2D convolutions, the plain definition).
Both run in the same process, alternately, on the same images, forward only and
forward + backward (gradient for the rendered image). ``--threads`` sets torch's and
the kernels' threads, default 1 (Glint keeps torch on one thread,
``core.kernels.threads``).
"""

from __future__ import annotations

import argparse

import torch

from bench.common import fast_vs_plain, fast_vs_plain_table
from core.evaluation.ssim import ssim, ssim_reference
from core.kernels.pool import set_kernel_threads

PLAIN = {
    "separable": ("compiled blur", "torch separable"),
    "window": ("torch separable", "2D window"),
}


def run(sizes: list[int], repeat: int, plain: str = "separable") -> list[dict]:
    rows = []
    for size in sizes:
        g = torch.Generator().manual_seed(size)
        ref = torch.rand(size, size, 3, generator=g)
        img = (ref + 0.1 * torch.randn(size, size, 3, generator=g)).clamp(0, 1)
        img.requires_grad_(True)
        if plain == "separable":
            pair = (
                lambda img=img, ref=ref: ssim(img, ref, compiled=True),
                lambda img=img, ref=ref: ssim(img, ref, compiled=False),
            )
        else:
            pair = (
                lambda img=img, ref=ref: ssim(img, ref, compiled=False),
                lambda img=img, ref=ref: ssim_reference(img, ref),
            )
        med = fast_vs_plain(
            *pair,
            (img,),
            None,
            repeat,
        )
        rows.append({"size": size, "label": f"{size}²", "plain": plain, **med})
    return rows


def format_table(rows: list[dict]) -> str:
    names = PLAIN[rows[0]["plain"]] if rows else PLAIN["separable"]
    return fast_vs_plain_table(rows, "image", names)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512, 800])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--plain", choices=sorted(PLAIN), default="separable")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    set_kernel_threads(args.threads)
    print(format_table(run(args.sizes, args.repeat, args.plain)))


if __name__ == "__main__":
    main()
