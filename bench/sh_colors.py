"""View-dependent SH colour (degree 3): compiled pass vs PyTorch, side by side.

    python -m bench.sh_colors [--n 20000 100000 300000] [--threads 2] [--repeat 15]

``Gaussians.colors`` runs once per rendered view: in every training step (with
gradients for the coefficients and the centres) and in every viewer frame (without).
``core.render.sh_compiled.sh_colors_fused`` is what it runs on CPU; ``core.render.sh.sh_to_rgb`` is
the PyTorch definition it is tested against. Both run in one process, alternately,
in Glint's thread layout (torch on one thread, the compiled kernels on ``--threads``).
"""

from __future__ import annotations

import argparse

import torch

from bench.common import fast_vs_plain, fast_vs_plain_table
from core.render.sh import sh_to_rgb
from core.render.sh_compiled import sh_colors_compiled

CAMERA = torch.tensor([0.0, -3.0, 0.5], dtype=torch.float64)


def run(sizes: list[int], repeat: int) -> list[dict]:
    rows = []
    for n in sizes:
        g = torch.Generator().manual_seed(n)
        means = torch.randn(n, 3, generator=g).requires_grad_(True)
        dc = torch.randn(n, 1, 3, generator=g).requires_grad_(True)
        rest = (0.1 * torch.randn(n, 15, 3, generator=g)).requires_grad_(True)
        med = fast_vs_plain(
            lambda m=means, d=dc, r=rest: sh_colors_compiled(3, d, r, m, CAMERA),
            lambda m=means, d=dc, r=rest: sh_to_rgb(3, torch.cat([d, r], 1), m - CAMERA.float()),
            (means, dc, rest),
            torch.randn(n, 3, generator=g),
            repeat,
        )
        rows.append({"n": n, "label": f"{n:,}", **med})
    return rows


def format_table(rows: list[dict]) -> str:
    return fast_vs_plain_table(rows, "Gaussians", ("compiled", "PyTorch"))


def main(argv: list[str] | None = None) -> None:
    from core.kernels.threads import configure_cpu_threads

    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--n", type=int, nargs="+", default=[20_000, 100_000, 300_000])
    ap.add_argument("--threads", type=int, default=0, help="kernel threads (0: every CPU)")
    ap.add_argument("--repeat", type=int, default=15)
    args = ap.parse_args(argv)
    configure_cpu_threads(args.threads or None)
    print(format_table(run(args.n, args.repeat)))


if __name__ == "__main__":
    main()
