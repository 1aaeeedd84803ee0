"""``bench/api_load.py`` runs end to end (a few clients, two seconds) so it cannot rot;
its wrk mode too where wrk is installed."""

from __future__ import annotations

import shutil

import pytest

from bench.api_load import main, percentile


def test_percentile_is_nearest_rank() -> None:
    values = [float(v) for v in range(1, 101)]
    assert percentile(values, 0.5) == 50.0 and percentile(values, 0.99) == 99.0
    assert percentile([3.0], 0.99) == 3.0


def test_api_load_smoke(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--clients", "5", "--duration", "2", "--without-job", "--size", "24"]
    assert main([*args, "--views", "6", "--interval", "0,0.5"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| without job |")]
    assert len(rows) == 2, out
    for row, interval in zip(rows, ("0", "0.5"), strict=True):
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[1] == "5" and cells[2] == interval, out
        assert int(cells[4]) > 0 and cells[5] == "0", out  # answers, no errors


@pytest.mark.skipif(shutil.which("wrk") is None, reason="wrk is not installed")
def test_api_load_wrk_smoke(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--clients", "5", "--duration", "2", "--without-job", "--size", "24", "--views", "6"]
    assert main([*args, "--wrk"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| without job |")]
    assert len(rows) == 1, out
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    assert cells[1] == "5" and cells[2] == "0" and cells[-1] == "wrk", out
    assert int(cells[4]) > 0 and cells[5] == "0" and float(cells[11]) > 0, out
