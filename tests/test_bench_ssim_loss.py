"""bench.ssim_loss runs both SSIM implementations and reports their ratios."""

from __future__ import annotations

import math

from bench.ssim_loss import format_table, run


def test_ssim_bench_times_both_implementations():
    rows = run([16, 24], repeat=1)
    assert [r["size"] for r in rows] == [16, 24]
    for r in rows:
        assert all(math.isfinite(r[k]) and r[k] > 0 for k in ("sf", "rf", "sb", "rb"))
    table = format_table(rows)
    assert "| 24² |" in table and table.count("×") == 4
