"""Time budgets: durations, the planned iteration count, and budgeted runs on the CPU."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from core.cli import main
from core.config import ConfigError, config_from_dict, format_duration, parse_duration
from core.model.schedule import Marks
from core.scene.synthetic import write_synthetic_scene
from core.training.budget import TimeBudget

ROOT = Path(__file__).resolve().parents[1]
TINY = {
    "init_points": 300,
    "envmap_resolution": 8,
    "eval": {"views": 1},
    "densify": {"max_gaussians": 1500},
    "outputs": {"mesh_resolution": 32},
}


@pytest.mark.parametrize(
    ("text", "seconds"),
    [("90s", 90), ("5m", 300), ("1h", 3600), ("1h30m", 5400), ("2.5m", 150), (45, 45), ("12", 12)],
)
def test_durations(text, seconds) -> None:
    assert parse_duration(text) == seconds
    assert parse_duration(format_duration(seconds)) == seconds


@pytest.mark.parametrize(
    "bad", ["0", 0, "-5m", "soon", "5x", "", "inf", "nan", "8d", "200h", "5m5m", True, None]
)
def test_bad_durations_name_the_problem(bad) -> None:
    with pytest.raises((ValueError, TypeError)):
        parse_duration(bad)
    if bad is not None:
        with pytest.raises(ConfigError, match="time_budget"):
            config_from_dict({"time_budget": bad})


def test_bad_duration_on_the_command_line_writes_nothing(tmp_path: Path, capsys) -> None:
    out = tmp_path / "run"
    assert main(["train", str(tmp_path), "--out", str(out), "--time=-5m"]) == 2
    assert "--time" in capsys.readouterr().err and not out.exists()
    assert main(["bench", str(tmp_path), "--out", str(out), "--time", "soon"]) == 2
    assert not out.exists()


def _budget(seconds: float, cap: int = 30_000) -> tuple[TimeBudget, object]:
    cfg = config_from_dict({"time_budget": seconds, "iterations": cap})
    b = TimeBudget.of(cfg)
    assert b is not None
    for _ in range(10):
        b.observe("rgb", 0.01, 1000)  # 10 µs per Gaussian-step
    return b, cfg


def no_overhead(n: int, steps: float) -> float:
    return 0.0


def test_the_plan_fills_the_time_left_and_keeps_the_phase_proportions() -> None:
    b, cfg = _budget(100.0)
    n = b.plan(cfg, 10, used=1.0, n_gaussians=1000, overhead=no_overhead)
    left = 99.0
    assert b.predict(cfg, n, 10, 1000, no_overhead) <= left
    assert b.predict(cfg, n + 1, 10, 1000, no_overhead) > left
    # later phases cost more per step than the RGB steps measured so far
    assert n < 10 + left / 0.01
    # the schedule is an iteration-sized run's of that length: the paper's proportions
    # once the short-run floors no longer bind
    big, cfg_big = _budget(2000.0)
    nb = big.plan(cfg_big, 10, 1.0, 1000, no_overhead)
    m = Marks.of(cfg_big.model_copy(update={"iterations": nb}))
    assert nb > 15_000
    assert m.geometry_start / nb == pytest.approx(3_000 / 30_000, abs=0.005)
    assert m.multiview_start / nb == pytest.approx(7_000 / 30_000, abs=0.005)
    # twice the time, about twice the iterations; the cap always wins
    b2, _ = _budget(200.0)
    assert b2.plan(cfg, 10, 1.0, 1000, no_overhead) > 1.8 * n
    b3, cfg3 = _budget(1e5, cap=500)
    assert b3.plan(cfg3, 10, 1.0, 1000, no_overhead) == 500


def test_a_new_plan_never_moves_a_passed_phase_mark_past_the_last_step() -> None:
    b, cfg = _budget(100.0)
    n = b.plan(cfg, 10, 1.0, 1000, no_overhead)
    geo = Marks.of(cfg.model_copy(update={"iterations": n})).geometry_start
    it = geo + 5  # in the geometry phase; steps turn out far cheaper than predicted
    b.cost = {"rgb": 1e-7, "geometry": 1e-7}
    n2 = b.plan(cfg, it, 20.0, 1000, no_overhead)
    assert Marks.of(cfg.model_copy(update={"iterations": n2})).geometry_start <= it - 1
    assert n2 > n  # it may grow, but the passed mark stays behind the last step


def _rows(run: Path) -> list[dict]:
    return [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]


def _used(ck: Path) -> float:
    x = torch.load(ck, map_location="cpu", weights_only=False)["extra"]
    return float(x["train_seconds"] + x["eval_seconds"] + x["io_seconds"])


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    return write_synthetic_scene(
        tmp_path_factory.mktemp("tb") / "s", "sphere", "glossy", n_train=8, n_test=2, size=24
    )


@pytest.fixture(scope="module")
def warm_kernels(tiny_scene: Path, tmp_path_factory) -> None:
    """Compile the numba kernels a run uses (raster, shading, meshing) before a budget is
    timed: on a fresh clone their caches are cold, the first evaluation then takes seconds
    of JIT compilation, and the plan, fitted to that, ended the 8 s run in its RGB phase.
    A budget cannot foresee a one-off compile; what is tested here is the plan."""
    from core.training.run import train_scene

    train_scene(tiny_scene, tmp_path_factory.mktemp("warm") / "run", config_from_dict(
        {**TINY, "iterations": 30}))  # fmt: skip


def test_a_budgeted_run_stops_in_time_with_complete_outputs(
    tiny_scene: Path, tmp_path, warm_kernels: None
) -> None:
    from core.training.run import train_scene

    budget = 8.0
    cfg = config_from_dict({**TINY, "time_budget": budget})
    run = tmp_path / "run"
    result, summary = train_scene(tiny_scene, run, cfg)
    assert result.status == "succeeded" and result.stopped_by == "time"
    used = _used(run / "checkpoint.pt")
    assert budget * 0.7 < used <= budget * 1.1 + 0.5
    rows = _rows(run)
    assert rows[-1]["iteration"] == result.iteration and rows[-1]["time_left"] >= 0
    phases = {r["phase"] for r in rows}
    assert phases == {"rgb", "geometry", "multiview"}  # the schedule was fitted, not cut
    for name in ("checkpoint.pt", "point_cloud.ply", "report.md", "mesh.ply", "plan.json"):
        assert (run / name).is_file(), name
    assert summary is not None and summary["mesh"]["faces"] > 0
    # the model reopens on the schedule it trained with: its last phase, not the cap's
    from core.model.trained import TrainedModel

    assert TrainedModel.open(run).phase.name == "multiview"


def test_a_killed_budgeted_run_resumes_with_the_time_left(
    tiny_scene: Path, warm_kernels: None, tmp_path
) -> None:
    """Checkpoints every few steps, so the kill lands early in the budget on any machine:
    with the default cadence (a fifth of the planned run, plus phase ends) a slow CI
    machine's first checkpoint past a fifth of the budget was the run's last, and the
    resumed run rightly had nothing left to do."""
    from core.training.run import train_scene

    budget = 14.0
    run = tmp_path / "run"
    sets = [
        "--set", "init_points=300", "--set", "envmap_resolution=8", "--set", "eval.views=1",
        "--set", "densify.max_gaussians=1500", "--set", "outputs.mesh=false",
        "--set", "checkpoint_every=5",
    ]  # fmt: skip
    cmd = [sys.executable, "-m", "core.cli", "train", str(tiny_scene), "--out", str(run)]
    proc = subprocess.Popen(
        [*cmd, "--time", f"{budget:g}s", "--quiet", *sets], cwd=ROOT,
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    ck = run / "checkpoint.pt"
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # a checkpoint past the first fifth of the run
            if ck.is_file() and any(r["iteration"] > 0 for r in _rows(run)):
                try:
                    if _used(ck) > 0.2 * budget:
                        break
                except Exception:  # caught mid-rename
                    pass
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(30)
    used_at_kill = _used(ck)
    assert 0.2 * budget < used_at_kill < 0.8 * budget
    cfg = config_from_dict(
        {**TINY, "time_budget": budget, "outputs": {"mesh": False}, "checkpoint_every": 5}
    )
    result, _ = train_scene(tiny_scene, run, cfg)  # resumes from the checkpoint
    assert result.status == "succeeded" and result.stopped_by == "time"
    used = _used(ck)
    assert used <= budget * 1.1 + 0.5  # the budget was not refilled
    assert used > used_at_kill


def test_a_phase_a_refit_cuts_short_still_ends_with_its_row(tiny_scene: Path, tmp_path) -> None:
    """A time budget's refit can move the next phase's mark to before the current step
    (the machine slowed down): the phase that step ran still ends with an evaluated row,
    labelled with the phase the step ran. (CI once recorded no geometry row at all.)"""
    from core.scene.formats import load_scene
    from core.training.trainer import Trainer

    cfg = config_from_dict({**TINY, "iterations": 60, "eval": {"views": 1, "every": 1000}})
    t = Trainer(load_scene(tiny_scene), cfg, tmp_path)
    t.setup(resume=False)
    real_step, cut = t.step, {}

    def step() -> dict[str, float]:
        out = real_step()
        it = t.iteration
        if not cut and t.current_phase(it - 1).name == "geometry" and it > t.marks.geometry_start:
            for k in range(t.sched.iterations - 1, it, -1):  # the longest schedule that cuts it
                m = Marks.of(cfg.model_copy(update={"iterations": k}))
                if (
                    m.geometry_start < it - 1
                    and m.multiview_start < it
                    and it not in m.boundaries()
                ):
                    t._resize_schedule(k)
                    cut["at"] = it
                    break
        return out

    t.step = step  # type: ignore[method-assign]
    t.train()
    assert cut, "no schedule moved the multi-view mark before a geometry step"
    rows = {r["iteration"]: r["phase"] for r in t.metrics.rows()}
    assert rows.get(cut["at"]) == "geometry"
    assert "multiview" in rows.values()
