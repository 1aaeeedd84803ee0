"""The GPU acceptance kit's dry run (CI): every stage in its CPU form, and its report.

A bare GPU machine gets one call to prove the CUDA path; this keeps the kit from rotting
between GPUs: the wheel lock still covers every import, and every stage still runs.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

import bench.gpu_wheels as gw
from bench.gpu_check import STAGES

ROOT = Path(__file__).resolve().parents[1]


def test_the_lock_covers_every_import_and_fits() -> None:
    res = gw.check_lock()
    assert res["problems"] == []
    assert res["total_mib"] < 64 and res["wheels"] >= 30
    names = {e["name"] for e in json.loads(gw.LOCK.read_text())["wheels"]}
    assert {"fastapi", "celery", "gsplat", "openimageio", "trimesh"} <= names
    assert not any(gw.TORCH_SIDE.match(n) for n in names)  # torch is the machine's


def test_a_stale_lock_is_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data = json.loads(gw.LOCK.read_text())
    dropped = next(e for e in data["wheels"] if e["name"] == "celery")
    data["wheels"] = [e for e in data["wheels"] if e is not dropped]
    for e in data["wheels"]:
        if e["name"] == "fastapi":
            e["version"] = "0.0.1"
    stale = tmp_path / "wheels.lock.json"
    stale.write_text(json.dumps(data))
    monkeypatch.setattr(gw, "LOCK", stale)
    res = gw.check_lock()
    problems = " | ".join(res["problems"])
    assert "celery (for celery) is neither in" in problems  # imported by worker/, not carried
    assert "fastapi: locked 0.0.1" in " | ".join(res["warnings"])  # drift: a warning
    # an image package below what the carried wheels need is a conflict with its fix
    assert "add it to the lock" in gw.check_image({"numpy": [">=999"]})[0]


@pytest.mark.skipif(shutil.which("redis-server") is None, reason="redis-server missing")
def test_dry_run_runs_every_stage_and_resumes(tmp_path: Path) -> None:
    out = tmp_path / "dry"
    cmd = ["bash", str(ROOT / "scripts" / "gpu_check.sh"), "--dry-run", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    report = json.loads((out / "gpu_check.json").read_text())
    assert report["dry_run"] is True
    for name in STAGES:
        assert report["stages"][name]["status"] == "ok", (name, report["stages"][name])
    speed = report["stages"]["speed"]["result"]["rows"][0]
    assert speed["full_step_ms"] > 0 and speed["deferred_fps"] > 0
    assert report["stages"]["parity"]["result"]["failures"] == []
    assert report["stages"]["worker"]["result"]["state"] == "succeeded"
    assert report["stages"]["train"]["result"]["extrapolated_30k_minutes"] > 0
    md = (out / "gpu_check.md").read_text()
    assert "| worker | ok |" in md and "## Speed" in md and "103.5 FPS" in md
    # a second call finds every stage done and redoes none
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0 and "[" not in again.stdout.split("report:")[0]
