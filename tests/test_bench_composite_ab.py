"""bench.composite_ab builds two kernel sources and times them against each other."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import composite_ab
from core.render.raster import cpu_simd

pytestmark = pytest.mark.skipif(
    cpu_simd.why_unavailable() is not None,
    reason=f"SIMD kernel not built here: {cpu_simd.why_unavailable()}",
)


def test_the_same_source_twice_gives_identical_outputs(tmp_path: Path, capsys):
    out = tmp_path / "ab.json"
    argv = ["--old", str(cpu_simd.SOURCE), "--rounds", "2", "--gaussians", "3000",
            "--size", "64", "--train-gaussians", "500", "2000", "--threads", "1",
            "--json", str(out)]  # fmt: skip
    assert composite_ab.main(argv) == 0
    rows = json.loads(out.read_text())
    assert [r["case"].split(",")[0] for r in rows][:2] == ["64² frame", "64² frame"]
    assert len(rows) == 6
    for r in rows:
        assert r["max_rel_diff"] == 0.0  # one source built once: the same kernel
        assert r["old_ms"] > 0 and r["new_ms"] > 0
        lo, hi = r["range"]
        assert lo <= r["new_over_old"] <= hi
    assert "| case | old ms |" in capsys.readouterr().out


def test_an_unknown_revision_is_named(tmp_path: Path):
    with pytest.raises(SystemExit, match="no-such-rev"):
        composite_ab.source_of("no-such-rev", tmp_path)


def test_zero_rounds_is_refused(capsys):
    with pytest.raises(SystemExit):
        composite_ab.main(["--old", str(cpu_simd.SOURCE), "--rounds", "0"])
    assert "--rounds" in capsys.readouterr().err
