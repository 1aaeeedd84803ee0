"""Glint's "cuda" code paths end to end on CPU, with gsplat replaced by its PyTorch twin.

The real kernels are only checked on a GPU (``tests/test_raster_cuda.py``); these
tests cover what sits around them and otherwise only ever runs on a GPU worker:
training with packed gsplat results (densification statistics scattered back from
``gaussian_ids``, the multi-view second pass) and the GPU benchmark's plain 3DGS
render, which hands gsplat SH coefficients instead of colours.
"""

from __future__ import annotations

import argparse
import math

import pytest
import torch

from bench.common import bench_camera
from bench.train_step import make_gaussians, plain_render, run
from core.config import config_from_dict
from core.render.raster import resolve_backend
from core.scene.synthetic import make_sphere_scene
from core.training.trainer import Trainer
from tests.gsplat_twin import twin_as_cuda  # noqa: F401  (fixture)

pytestmark = pytest.mark.usefixtures("twin_as_cuda")


def _train(backend: str, out, iterations: int) -> tuple[Trainer, list[dict[str, float]]]:
    """Train the small glossy sphere; returns the trainer and each step's loss terms."""
    scene = make_sphere_scene("glossy", n_train=6, n_test=2, size=40, samples=2)
    cfg = config_from_dict(
        {
            "iterations": iterations,
            "device": "cpu",
            "backend": backend,
            "init_points": 400,
            "envmap_resolution": 8,
            "seed": 3,
            # one order on both: 'auto' is plane order on the reference, centre on gsplat
            "splat_order": "centre",
            # high enough that only some Gaussians qualify: which ones depends on the
            # screen gradients scattered back through ``gaussian_ids``
            "densify": {"grad_threshold": 3e-3},
            "eval": {"every": iterations, "views": 2},
        }
    )
    t = Trainer(scene, cfg, out)
    t.setup(resume=False)
    steps = []
    while t.iteration < iterations:
        steps.append(t.step())
    return t, steps


def test_cuda_backend_resolves_to_the_twin():
    assert resolve_backend("cuda", "cpu") == "cuda"


def test_training_through_the_cuda_path_matches_the_reference_backend(tmp_path):
    """Same seed and schedule, densification included: packed gsplat results (rows per
    visible Gaussian, ``gaussian_ids``) must train exactly what the reference trains."""
    t_cu, s_cu = _train("cuda", tmp_path / "cuda", 60)
    t_ref, s_ref = _train("reference", tmp_path / "ref", 60)
    assert not any("skipped" in s for s in s_cu), "a step produced a non-finite loss"
    grown = sum(s.get("densify_cloned", 0) + s.get("densify_split", 0) for s in s_cu)
    assert grown > 0, "packed screen gradients never reached densification"
    # The twin composites like the reference and only gsplat's projection differs
    # (~1e-5 here), so the same Gaussians are cloned and split and end up the same.
    assert t_cu.gaussians.num == t_ref.gaussians.num
    for name, p in t_ref.gaussians.params.items():
        err = float((t_cu.gaussians.params[name].detach() - p.detach()).abs().max())
        assert err < 1e-3, f"{name} differs by {err:.2e} after training"
    for a, b in zip(s_cu, s_ref, strict=True):
        assert a["rgb"] == pytest.approx(b["rgb"], rel=1e-3)
    psnr = t_cu.evaluate()["psnr"]
    assert math.isfinite(psnr) and psnr > 12
    assert psnr == pytest.approx(t_ref.evaluate()["psnr"], abs=0.2)


def test_plain_gsplat_render_matches_ours_with_the_same_sh():
    """The GPU benchmark's baseline renders the same image as our 3-channel path."""
    cam = bench_camera(40)
    gs = make_gaussians(1500, torch.device("cpu"))
    with torch.no_grad():
        via_gsplat_sh = plain_render(gs, cam, "cuda")
        ours = plain_render(gs, cam, "reference")
    assert float((ours < 0.999).float().mean()) > 0.2  # the Gaussians cover the image
    err = float((via_gsplat_sh - ours).abs().max())
    assert err < 2e-3, f"SH colours or compositing differ: max error {err:.2e}"


def test_gpu_benchmark_runs_through_the_cuda_path():
    args = argparse.Namespace(
        device="cpu", backend="cuda", size=24, n=300, envmap=8, repeat=1, warmup=0,
        threads=1, split_threads=False, no_roughness=False, compare_order=None,
    )  # fmt: skip
    res = run(args)
    assert res["backend"] == "cuda"
    assert "full step (multi-view phase)" in [r["case"] for r in res["rows"]]
    assert all(math.isfinite(r["ms"]) and r["ms"] > 0 for r in res["rows"])
