"""View-dependent SH colour (degree 3): compiled pass vs PyTorch, side by side.

    python -m bench.sh_colors [--n 20000 100000 300000] [--threads 2] [--repeat 15]

``Gaussians.colors`` runs once per rendered view: in every training step (with
gradients for the coefficients and the centres) and in every viewer frame (without).
``core.sh_fused.sh_colors_fused`` is what it runs on CPU; ``core.sh.sh_to_rgb`` is
the PyTorch definition it is tested against. Both run in one process, alternately,
in Glint's thread layout (torch on one thread, the compiled kernels on ``--threads``).
"""

from __future__ import annotations

import argparse

import torch

from bench.common import interleaved_medians, machine_line
from core.sh import sh_to_rgb
from core.sh_fused import sh_colors_fused

CAMERA = torch.tensor([0.0, -3.0, 0.5], dtype=torch.float64)


def run(sizes: list[int], repeat: int) -> list[dict]:
    rows = []
    for n in sizes:
        g = torch.Generator().manual_seed(n)
        means = torch.randn(n, 3, generator=g).requires_grad_(True)
        dc = torch.randn(n, 1, 3, generator=g).requires_grad_(True)
        rest = (0.1 * torch.randn(n, 15, 3, generator=g)).requires_grad_(True)
        weight = torch.randn(n, 3, generator=g)
        params = (means, dc, rest)

        def torch_path(means=means, dc=dc, rest=rest) -> torch.Tensor:
            return sh_to_rgb(3, torch.cat([dc, rest], 1), means - CAMERA.float())

        def fused_path(means=means, dc=dc, rest=rest) -> torch.Tensor:
            return sh_colors_fused(3, dc, rest, means, CAMERA)

        def fwd(f) -> None:
            with torch.no_grad():
                f()

        def fwd_bwd(f, weight=weight, params=params) -> None:
            f().backward(weight)
            for p in params:
                p.grad = None

        med = interleaved_medians(
            {
                "ff": lambda: fwd(fused_path),
                "tf": lambda: fwd(torch_path),
                "fb": lambda: fwd_bwd(fused_path),
                "tb": lambda: fwd_bwd(torch_path),
            },
            repeat,
        )
        rows.append({"n": n, **med})
    return rows


def format_table(rows: list[dict]) -> str:
    lines = [
        f"Machine: {machine_line()}",
        "",
        "| Gaussians | forward: compiled | PyTorch | ratio | fwd+bwd: compiled | PyTorch | ratio |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n']:,} | {r['ff']:.2f} ms | {r['tf']:.2f} ms | {r['tf'] / r['ff']:.2f}× "
            f"| {r['fb']:.2f} ms | {r['tb']:.2f} ms | {r['tb'] / r['fb']:.2f}× |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    from core.threads import configure_cpu_threads

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
