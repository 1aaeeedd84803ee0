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
