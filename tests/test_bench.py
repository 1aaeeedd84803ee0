"""``glint bench`` end to end on a tiny generated scene, resumption, and ``glint eval``/``mesh``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from core.benchmark.configs import CONFIGS, LABELS, TABLE_ORDER, bench_config, parse_configs
from core.benchmark.tables import mean_curve, results_table
from core.cli import main
from core.errors import GlintError
from core.evaluation.evaluate import EVAL_FILE
from core.scene.synthetic import SPHERE_RADIUS, surface_points, write_synthetic_scene

BUDGET = 12
SMALL = [
    "--set", "init_points=400",
    "--set", "densify.max_gaussians=2000",
    "--set", "envmap_resolution=8",
]  # fmt: skip
FAST_EVAL = ["--points", "20000", "--mesh-resolution", "40", "--threads", "1"]


def _write_gt_points(scene: Path) -> None:
    """Ground-truth surface points in the dev data's layout (gt_points.ply + seen mask)."""
    p, n = surface_points("sphere", 5000, seed=1)
    arr = np.zeros(len(p), dtype=[(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz")])
    for i, k in enumerate("xyz"):
        arr[k] = p[:, i].numpy()
        arr["n" + k] = n[:, i].numpy()
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(scene / "gt_points.ply"))
    np.save(scene / "gt_points_seen.npy", np.ones(len(p), dtype=bool))


@pytest.fixture(scope="module", autouse=True)
def _restore_torch_threads():
    """``--threads`` sets torch's thread count for the whole process: undo it."""
    import torch

    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("bench")
    scene = write_synthetic_scene(
        root / "tiny", "sphere", "glossy", n_train=6, n_test=2, size=20, seed=0
    )
    _write_gt_points(scene)
    out = root / "out"
    args = ["bench", str(scene), "--budget", str(BUDGET), "--out", str(out)]
    rc = main([*args, "--configs", "full,sh_only", "--quiet", *SMALL, *FAST_EVAL])
    assert rc == 0
    return scene, out


def test_bench_writes_both_rows_and_the_figure(bench_run) -> None:
    _, out = bench_run
    md = (out / "bench.md").read_text()
    assert f"| {LABELS['full']} |" in md and f"| {LABELS['sh_only']} |" in md
    assert "2/2 runs finished" in md
    assert "At equal wall time" in md and "Training seconds until CD×10²" in md
    assert f"Command: `glint bench {bench_run[0]} --budget {BUDGET}" in md
    assert (out / "error_vs_time.png").stat().st_size > 0
    assert (out / "error_vs_time_tiny.png").stat().st_size > 0
    for cfg in ("full", "sh_only"):
        run = out / "tiny" / cfg
        ev = json.loads((run / EVAL_FILE).read_text())
        assert ev["iteration"] == BUDGET
        s = ev["summary"]
        assert np.isfinite(s["cd_x100"]) and s["cd_x100"] > 0 and s["dropped"] >= 0
        assert np.isfinite(s["psnr"]) and 0 < s["ssim"] <= 1 and s["fps"] > 0
        assert s["lpips"] == "unavailable" or isinstance(s["lpips"], float)
        assert ev["image"]["views"] == 2 and ev["train_seconds"] > 0
        assert ev["chamfer"]["sampled"] == 20000
        assert all((run / f).is_file() for f in ("mesh.ply", "mesh.obj", "mesh.glb"))
        assert "## Evaluation" in (run / "report.md").read_text()
    cfg_full = json.loads((out / "tiny" / "full" / "config.json").read_text())
    cfg_sh = json.loads((out / "tiny" / "sh_only" / "config.json").read_text())
    assert cfg_full["ablation"]["deferred_shading"] and cfg_full["init_points"] == 400
    assert cfg_sh["ablation"] == {**cfg_full["ablation"], **CONFIGS["sh_only"]}
    # the baseline composites as 3DGS does; the full model in plane order where it can
    assert (cfg_sh["splat_order"], cfg_full["splat_order"]) == ("centre", "auto")
    plan = json.loads((out / "tiny" / "full" / "plan.json").read_text())
    assert plan["decisions"]["envmap"]["value"] is True


def test_second_invocation_skips_finished_cells(bench_run) -> None:
    scene, out = bench_run
    evals = [out / "tiny" / c / EVAL_FILE for c in ("full", "sh_only")]
    ckpt = out / "tiny" / "full" / "checkpoint.pt"
    before = [p.stat().st_mtime_ns for p in [*evals, ckpt]]
    args = ["bench", str(scene), "--budget", str(BUDGET), "--out", str(out)]
    assert main([*args, "--configs", "full,sh_only", "--quiet", *SMALL, *FAST_EVAL]) == 0
    assert [p.stat().st_mtime_ns for p in [*evals, ckpt]] == before
    assert "| Full model |" in (out / "bench.md").read_text()


def test_retime_fps_updates_every_finished_cell_without_training(bench_run, tmp_path) -> None:
    import shutil

    scene, out = bench_run
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    ckpt = copy / "tiny" / "full" / "checkpoint.pt"
    before = ckpt.stat().st_mtime_ns
    args = ["bench", str(scene), "--budget", str(BUDGET), "--out", str(copy), "--retime-fps"]
    assert main([*args, "--configs", "full,sh_only", "--quiet", *SMALL, *FAST_EVAL]) == 0
    for cfg in ("full", "sh_only"):
        ev = json.loads((copy / "tiny" / cfg / EVAL_FILE).read_text())
        assert ev["fps"]["refreshed"] is True and ev["summary"]["fps"] == ev["fps"]["fps"] > 0
    assert ckpt.stat().st_mtime_ns == before
    assert "re-timed back to back" in (copy / "bench.md").read_text()


def test_a_cell_from_another_configuration_is_not_reused(bench_run) -> None:
    scene, out = bench_run
    args = ["bench", str(scene), "--budget", str(BUDGET + 1), "--out", str(out)]
    assert main([*args, "--configs", "full", "--quiet", *SMALL, *FAST_EVAL]) == 2
    assert json.loads((out / "tiny" / "full" / EVAL_FILE).read_text())["iteration"] == BUDGET


def test_interrupted_cell_resumes_from_its_checkpoint(bench_run, tmp_path) -> None:
    """A cell stopped mid-training is trained on from its checkpoint, not restarted."""
    from core.training.run import train_scene

    scene, _ = bench_run
    out = tmp_path / "out"
    run = out / "tiny" / "full"
    base = {"init_points": 400, "densify": {"max_gaussians": 2000}, "envmap_resolution": 8}
    cfg = bench_config("full", BUDGET, 1.0, base)
    seen = {"it": 0}

    def on_event(e: dict) -> None:
        if e.get("type") == "progress":
            seen["it"] = e["iteration"]

    result, _ = train_scene(
        scene, run, cfg, on_event=on_event, should_stop=lambda: seen["it"] >= BUDGET // 2
    )
    assert result.status == "cancelled" and result.iteration == BUDGET // 2
    rows_before = (run / "metrics.jsonl").read_text().splitlines()
    assert not (run / EVAL_FILE).exists()
    args = ["bench", str(scene), "--budget", str(BUDGET), "--out", str(out)]
    assert main([*args, "--configs", "full", "--quiet", *SMALL, *FAST_EVAL]) == 0
    assert json.loads((run / EVAL_FILE).read_text())["iteration"] == BUDGET
    rows_after = (run / "metrics.jsonl").read_text().splitlines()
    # the rows recorded before the interruption (wall times included) are kept as they were
    kept = [r for r in rows_after if json.loads(r)["iteration"] <= BUDGET // 2]
    assert kept == rows_before and len(rows_after) > len(rows_before)


def test_glint_eval_and_mesh_commands_on_a_run(bench_run, capsys) -> None:
    scene, out = bench_run
    run = out / "tiny" / "full"
    assert main(["mesh", str(run), "--mesh-resolution", "32", "--threads", "1"]) == 0
    info = json.loads((run / "mesh.json").read_text())
    assert info["fusion"]["shape"][0] <= 34 and info["faces"] > 0
    # the explicit --gt path and the scene recorded by the bench agree
    assert main(["eval", str(run), "--gt", str(scene), *FAST_EVAL]) == 0
    printed = capsys.readouterr().out
    assert '"cd_x100"' in printed
    ev = json.loads((run / EVAL_FILE).read_text())
    # a sphere of radius 0.6 after 20 iterations: its mesh is near, not on, the surface
    assert ev["chamfer"]["cd"] < SPHERE_RADIUS


def test_eval_needs_a_checkpoint_and_a_scene(tmp_path) -> None:
    with pytest.raises(GlintError, match="checkpoint"):
        from core.evaluation.evaluate import evaluate_run

        evaluate_run(tmp_path)
    assert main(["eval", str(tmp_path)]) == 2


def test_config_names_and_overrides() -> None:
    assert parse_configs("full, no_multi,full") == ["full", "no_multi"]
    with pytest.raises(GlintError, match="unknown configuration"):
        parse_configs("full,no_such")
    cfg = bench_config("eq5_depth", 300, 0.5, {"loss": {"scale": 50.0}})
    assert cfg.iterations == 300 and cfg.resolution_scale == 0.5
    assert cfg.ablation.planar_depth is False and cfg.ablation.multi_view is True
    assert cfg.loss.scale == 50.0
    # the env map is forced on where deferred shading is on, never where it is off
    assert cfg.plan_overrides == {"envmap": True}
    assert bench_config("no_deferred", 300, 0.5).plan_overrides == {}
    assert bench_config("sh_only", 300, 0.5).plan_overrides == {}
    mine = bench_config("full", 300, 0.5, {"plan_overrides": {"envmap": False}})
    assert mine.plan_overrides == {"envmap": False}
    # the volume-init row starts 30% inside the hull; the full model starts on it
    assert bench_config("volume_init", 300, 0.5).init_volume_fraction == 0.3
    assert bench_config("full", 300, 0.5).init_volume_fraction == 0.0
    # a configuration's section settings merge into the base's section
    seeded = bench_config("seed_behind", 300, 0.5, {"densify": {"max_gaussians": 900}})
    assert seeded.densify.seed_behind == 0.25 and seeded.densify.max_gaussians == 900
    assert bench_config("full", 300, 0.5).densify.seed_behind == 0.0
    # the silhouette-stop row ends the term at 80% of the run; the base's phases merge in
    stop = bench_config("sil_stop", 300, 0.5, {"phases": {"geometry_start": 2000}})
    assert stop.phases.silhouette_until == 0.8 and stop.phases.geometry_start == 2000
    assert bench_config("full", 300, 0.5).phases.silhouette_until == 1.0


def test_table_marks_the_best_value_per_column() -> None:
    rows = {
        "full": {"cd_x100": 0.85, "psnr": 29.43, "train_seconds": 10.0},
        "no_multi": {"cd_x100": 1.01, "psnr": 30.16, "train_seconds": 9.0},
    }
    table = results_table(rows)
    full = next(line for line in table.splitlines() if line.startswith("| Full model"))
    no_multi = next(line for line in table.splitlines() if line.startswith("| w/o L_multi"))
    assert "**0.850**" in full and "**30.16**" in no_multi
    assert "**" not in full.split("|")[4]  # PSNR of the full model is not the best
    assert table.splitlines().index(full) > table.splitlines().index(no_multi)  # paper order


def test_mean_curve_averages_scenes_at_shared_iterations() -> None:
    a = [{"iteration": i, "wall_time": float(i), "psnr": 20.0, "phase": "rgb"} for i in (0, 5, 10)]
    b = [{"iteration": i, "wall_time": 2.0 * i, "psnr": 30.0, "phase": "rgb"} for i in (0, 10)]
    m = mean_curve([a, b])
    assert [r["iteration"] for r in m] == [0, 10]
    assert m[1]["wall_time"] == 15.0 and m[1]["psnr"] == 25.0


def test_equal_time_and_time_to_reach_interpolate_the_recorded_points() -> None:
    from core.benchmark.tables import equal_time_rows, reach_table, time_to_reach, value_at

    fast = [
        {"wall_time": 0.0, "psnr": 20.0, "cd_x100": 4.0},
        {"wall_time": 10.0, "psnr": 30.0},
        {"wall_time": 20.0, "psnr": 32.0, "cd_x100": 2.0},
    ]
    slow = [
        {"wall_time": 0.0, "psnr": 20.0, "cd_x100": 4.0},
        {"wall_time": 40.0, "psnr": 36.0, "cd_x100": 1.0},
    ]
    assert value_at(fast, "psnr", 5.0) == 25.0 and value_at(fast, "cd_x100", 10.0) == 3.0
    assert value_at(fast, "psnr", 25.0) is None  # never extrapolated
    t, rows = equal_time_rows({"full": slow, "sh_only": fast})
    assert t == 20.0 and rows["full"]["psnr"] == 28.0 and rows["full"]["cd_x100"] == 2.5
    assert time_to_reach(slow, "cd_x100", 2.5) == 20.0
    assert time_to_reach(fast, "cd_x100", 1.0) is None
    table = reach_table({"full": slow, "sh_only": fast}, None)
    assert table is not None and "≤ 2.000" in table  # the worst final figure
    assert "not reached" in reach_table({"full": slow, "sh_only": fast}, 1.5)


def test_bench_configs_take_a_time_budget() -> None:
    cfg = bench_config("full", None, 1.0, time_budget=90.0)
    assert cfg.time_budget == 90.0 and cfg.iterations == 30_000
    both = bench_config("sh_only", 500, 0.5, time_budget=60.0)
    assert (both.iterations, both.time_budget) == (500, 60.0)


def test_paper_row_switches_off_every_addition_and_full_keeps_them() -> None:
    additions = ("silhouette", "one_sided", "grazing_opacity", "same_surface_normals",
                 "facing_depth", "roughness", "fresnel", "mask_coverage")  # fmt: skip
    paper, full = bench_config("paper", 300, 0.5), bench_config("full", 300, 0.5)
    for name in additions:
        assert getattr(paper.ablation, name) is False, name
        assert getattr(full.ablation, name) is True, name
    assert bench_config("all_angles", 300, 0.5).ablation.facing_depth is False
    assert bench_config("central_normals", 300, 0.5).ablation.same_surface_normals is False
    assert bench_config("no_mask_loss", 300, 0.5).ablation.mask_coverage is False
    rough = bench_config("no_roughness", 300, 0.5)
    assert rough.ablation.roughness is False and rough.ablation.deferred_shading is True
    assert rough.plan_overrides == {"envmap": True}  # the env map stays: only mirror lookups
    assert parse_configs("no_roughness") == ["no_roughness"]
    assert bench_config("no_fresnel", 300, 0.5).ablation.fresnel is False
    assert "Fresnel" in LABELS["no_fresnel"] and "no_fresnel" in TABLE_ORDER
    assert "roughness" in LABELS["no_roughness"] and "no_roughness" in TABLE_ORDER
    # every configuration has a label and a place in the table
    assert set(LABELS) == set(CONFIGS) == set(TABLE_ORDER)
