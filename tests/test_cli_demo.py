"""`glint demo`, the README's main job, end to end at a tiny size."""

from __future__ import annotations

import json

from core.cli import DEMO_DEFAULTS, main


def test_demo_generates_a_scene_trains_and_writes_outputs(tmp_path, capsys):
    out = tmp_path / "demo"
    rc = main(["demo", "--out", str(out), "--size", "24", "--iterations", "40", "--quiet"])
    assert rc == 0
    assert (out / "scene" / "transforms_train.json").is_file()
    run = out / "run"
    for name in ("checkpoint.pt", "point_cloud.ply", "plan.json", "report.md", "metrics.jsonl"):
        assert (run / name).is_file(), name
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["iterations"] == 40  # the command line wins over the demo's defaults
    assert cfg["antialiased"] is DEMO_DEFAULTS["antialiased"]
    assert "held-out PSNR" in capsys.readouterr().out
