"""bench.ssim_loss and bench.sh_colors run both implementations and report ratios."""

from __future__ import annotations

import math

import pytest

from bench.ssim_loss import format_table, run


@pytest.mark.parametrize(
    ("plain", "names"), [("separable", "compiled blur"), ("window", "2D window")]
)
def test_ssim_bench_times_both_implementations(plain, names):
    rows = run([16, 24], repeat=1, plain=plain)
    assert [r["size"] for r in rows] == [16, 24]
    for r in rows:
        assert all(math.isfinite(r[k]) and r[k] > 0 for k in ("ff", "pf", "fb", "pb"))
    table = format_table(rows)
    assert "| 24² |" in table and table.count("×") == 4 and names in table


def test_sh_colors_bench_times_both_paths():
    from bench.sh_colors import format_table as sh_table
    from bench.sh_colors import run as sh_run

    rows = sh_run([50, 80], repeat=1)
    assert [r["n"] for r in rows] == [50, 80]
    for r in rows:
        assert all(math.isfinite(r[k]) and r[k] > 0 for k in ("ff", "pf", "fb", "pb"))
    assert sh_table(rows).count("×") == 4


def test_frame_time_bench_renders_the_viewers_model(capsys):
    """bench.frame_time renders the viewer benchmark's model through the viewer's call."""
    import json

    import torch

    from bench.frame_time import main as frame_time
    from core.kernels import pool

    before = (torch.get_num_threads(), pool._KERNEL_THREADS)
    try:
        args = ["--gaussians", "2000", "--sizes", "24", "40", "--repeat", "2", "--threads", "1"]
        assert frame_time(args) == 0
    finally:  # the bench sets the process's thread layout
        torch.set_num_threads(before[0])
        pool.set_kernel_threads(before[1])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["gaussians"] == 2000 and out["channel"] == "final"
    assert [r["size"] for r in out["rows"]] == [24, 40]
    assert all(0 < r["min_ms"] <= r["median_ms"] for r in out["rows"])
