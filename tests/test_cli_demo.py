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


def test_a_finished_run_with_another_config_is_refused_not_reported(tmp_path, capsys):
    """`glint demo --set ...` on a folder holding a plain demo used to print the plain
    run's figures as the new configuration's; it now names what differs, and
    --overwrite trains again."""
    out = tmp_path / "demo"
    base = ["demo", "--out", str(out), "--size", "24", "--iterations", "30", "--quiet"]
    base += ["--set", "outputs.mesh_resolution=48"]  # the mesh is not what this is about
    assert main(base) == 0
    capsys.readouterr()
    assert main(base) == 0  # the same configuration: the finished run is reported again
    assert "held-out PSNR" in capsys.readouterr().out
    changed = [*base, "--set", "ablation.silhouette=false"]
    assert main(changed) == 2
    err = capsys.readouterr().err
    assert "ablation.silhouette: true -> false" in err and "--overwrite" in err
    cfg = json.loads((out / "run" / "config.json").read_text())
    assert cfg["ablation"]["silhouette"] is True  # the old run's record is untouched
    assert main([*changed, "--overwrite"]) == 0
    cfg = json.loads((out / "run" / "config.json").read_text())
    assert cfg["ablation"]["silhouette"] is False
