"""A run trained with a backend the viewer's device lacks still renders.

GPU workers may train with ``backend: cuda``; the API server that hosts the viewer
often has no GPU. Before ``frame_backend`` every frame of such a run failed with
"rasteriser backend 'cuda' is unavailable".
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from core.config import config_from_dict
from core.model.checkpoint import load_checkpoint, save_checkpoint
from core.render.raster import resolve_backend
from core.scene.cameras import Camera, Intrinsics
from core.scene.synthetic import make_sphere_scene
from core.training.run import train_scene
from viewer_web.renderer import frame_backend, load_model, render_channel

CPU = torch.device("cpu")


def test_a_backend_this_device_has_is_kept():
    assert frame_backend("reference", CPU) == "reference"
    assert frame_backend("auto", CPU) == resolve_backend("auto", CPU)


def test_a_backend_this_device_lacks_gives_way_to_auto():
    assert frame_backend("cuda", CPU) == resolve_backend("auto", CPU)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cuda-run")
    scene = make_sphere_scene("glossy", n_train=4, n_test=1, size=24, samples=1)
    cfg = config_from_dict(
        {"iterations": 8, "device": "cpu", "backend": "auto", "init_points": 300,
         "envmap_resolution": 8}
    )  # fmt: skip
    train_scene(scene, out, cfg, export=False)
    return out


def _as_trained_with(run_dir: Path, backend: str, name: str) -> Path:
    """A copy of the run's checkpoint whose saved config names ``backend``."""
    ck = load_checkpoint(run_dir / "checkpoint.pt", CPU)
    extra = dict(ck.extra)
    extra["config"] = {**extra["config"], "backend": backend}
    return save_checkpoint(run_dir / name, ck.gaussians, extra)


def test_a_run_trained_on_cuda_renders_on_a_cpu_server(run_dir: Path):
    on_gpu = load_model(_as_trained_with(run_dir, "cuda", "gpu.pt"), CPU)
    local = load_model(run_dir / "checkpoint.pt", CPU)
    assert on_gpu.cfg.backend == "cuda"  # the run's record is left as it was
    assert on_gpu.backend == local.backend == resolve_backend("auto", CPU)
    assert on_gpu.summary()["backend"] == on_gpu.backend
    cam = Camera.look_at([0.0, 0.3, 3.5], [0, 0, 0], [0, 1, 0], Intrinsics(30, 30, 16, 16, 32, 32))
    for channel in ("final", "normal", "depth"):
        got, want = render_channel(on_gpu, cam, channel), render_channel(local, cam, channel)
        assert got.shape == (32, 32, 3)
        np.testing.assert_array_equal(got, want)
    assert int(render_channel(on_gpu, cam, "alpha").max()) > 128  # the sphere is in view
