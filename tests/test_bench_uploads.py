"""bench/uploads.py at a tiny size: every row measured, and the resumed client sends
exactly what the dead one had not."""

from __future__ import annotations

from pathlib import Path

from bench.uploads import run, table


def test_bench_uploads_smoke(tmp_path: Path) -> None:
    rows = run(3, 1, [1], tmp_path)
    assert [r["how"] for r in rows] == ["multipart", "chunks 1 MiB", "resumed (1 MiB chunks)"]
    resumed = rows[-1]
    assert 0 < resumed["before_mb"] < 3
    assert abs(resumed["before_mb"] + resumed["sent_mb"] - 3) < 1e-9  # MB, nothing twice
    assert all(r["seconds"] > 0 for r in rows)
    assert "| resumed (1 MiB chunks) |" in table(rows, 3)
