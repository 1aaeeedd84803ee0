"""Grazing opacity (core.render.grazing): the learned edge-on fade and where it acts."""

from __future__ import annotations

import math

import pytest
import torch

from core.config import TrainConfig
from core.model.checkpoint import load_checkpoint, save_checkpoint
from core.model.trained import TrainedModel
from core.render.gaussians import Gaussians
from core.render.grazing import (
    EXPONENT,
    GRAZE_KEY,
    INIT_LOGIT,
    add_grazing_state,
    grazing_factor,
)
from core.render.view_opacity import view_opacity_scale
from core.scene.cameras import Camera, Intrinsics
from core.training.optim import make_optimizers


def one_disc(k: float) -> Gaussians:
    """A flat Gaussian at the origin with normal +z and grazing strength ``k``."""
    g = Gaussians.from_points(torch.zeros(1, 3), radius=0.1)
    g.params["log_scales"].data[:] = torch.log(torch.tensor([[0.1, 0.1, 1e-4]]))
    g.params["quats"].data[:] = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    add_grazing_state(g)
    g.params[GRAZE_KEY].data[:] = math.log(k / (1 - k))
    return g


def camera_at(angle_deg: float) -> Camera:
    """A camera 3 units from the origin, ``angle_deg`` from the disc's normal."""
    a = math.radians(angle_deg)
    eye = [3 * math.sin(a), 0.0, 3 * math.cos(a)]
    up = [0.0, 1.0, 0.0]
    return Camera.look_at(eye, [0.0, 0.0, 0.0], up, Intrinsics(50, 50, 16, 16, 32, 32))


@pytest.mark.parametrize("angle", [0.0, 30.0, 60.0, 80.0, 90.0])
def test_the_factor_is_one_face_on_and_one_minus_k_edge_on(angle):
    k = 0.6
    f = grazing_factor(one_disc(k), camera_at(angle))
    cos = abs(math.cos(math.radians(angle)))
    expected = 1 - k * (1 - cos) ** EXPONENT
    assert f is not None
    assert float(f.detach()[0]) == pytest.approx(expected, abs=1e-5)


def test_seen_from_behind_fades_the_same():
    g = one_disc(0.5)
    assert float(grazing_factor(g, camera_at(70.0)).detach()[0]) == pytest.approx(
        float(grazing_factor(g, camera_at(110.0)).detach()[0]), abs=1e-5
    )


def test_gradient_reaches_the_logits_only():
    g = one_disc(0.3)
    f = grazing_factor(g, camera_at(75.0))
    f.sum().backward()
    assert g.params[GRAZE_KEY].grad is not None and float(g.params[GRAZE_KEY].grad.abs()) > 0
    for key in ("means", "quats", "log_scales"):
        grad = g.params[key].grad
        assert grad is None or float(grad.abs().sum()) == 0.0


def test_new_state_starts_near_no_fade_and_trains():
    g = Gaussians.from_points(torch.randn(5, 3))
    add_grazing_state(g)
    k = torch.sigmoid(g.params[GRAZE_KEY]).detach()
    assert torch.allclose(k, torch.sigmoid(torch.tensor(INIT_LOGIT)).expand(5))
    assert float(k.max()) < 0.05
    opts = make_optimizers(g, TrainConfig(iterations=10), 1.0)
    assert GRAZE_KEY in opts


def test_models_without_the_state_render_unchanged():
    g = Gaussians.from_points(torch.randn(5, 3))
    assert grazing_factor(g, camera_at(0.0)) is None
    assert view_opacity_scale(g, camera_at(0.0), one_sided=True, grazing=True) is None
    assert view_opacity_scale(g, camera_at(0.0), one_sided=False, grazing=False) is None


def test_a_trained_model_renders_the_fade(tmp_path):
    g = one_disc(0.9)
    cam = camera_at(80.0)
    cfg = TrainConfig(iterations=10)
    model = TrainedModel(
        gaussians=g, envmap=None, config=cfg, plan=None, iteration=10,
        device=torch.device("cpu"), backend="auto", cameras=[cam],
    )  # fmt: skip
    faded = float(model.render(cam, ("alpha",)).gbuffer.alpha.max())
    no_fade = TrainConfig(iterations=10, ablation={"grazing_opacity": False})
    plain = TrainedModel(
        gaussians=g, envmap=None, config=no_fade, plan=None, iteration=10,
        device=torch.device("cpu"), backend="auto", cameras=[cam],
    )  # fmt: skip
    unfaded = float(plain.render(cam, ("alpha",)).gbuffer.alpha.max())
    cos = math.cos(math.radians(80.0))
    assert faded == pytest.approx(unfaded * (1 - 0.9 * (1 - cos) ** EXPONENT), rel=0.02)
    path = tmp_path / "ck.pt"
    save_checkpoint(path, g, {"iteration": 10})
    back = load_checkpoint(path, "cpu").gaussians
    torch.testing.assert_close(back.params[GRAZE_KEY], g.params[GRAZE_KEY])
