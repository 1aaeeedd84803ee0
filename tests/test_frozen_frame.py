"""A frozen model's frame drops the Gaussians a view cannot show, and renders the same."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from bench.viewer import seen_from_outside, sphere_model
from core.config import TrainConfig
from core.model.checkpoint import save_checkpoint
from core.model.trained import TrainedModel
from core.render.envmap import EnvMap, texel_directions
from core.render.gaussians import Gaussians
from core.render.raster.projection import ALPHA_MIN
from core.render.view_opacity import view_opacity_scale, visible_index
from core.scene.cameras import Camera, Intrinsics
from core.scene.synthetic import default_env


def test_visible_index_keeps_what_can_reach_the_alpha_floor() -> None:
    o = torch.tensor([0.5, ALPHA_MIN, ALPHA_MIN * 0.99, 0.0, float("nan"), 1.0])
    assert visible_index(o).tolist() == [0, 1, 5]
    assert visible_index(torch.tensor([0.2, 0.9])) is None


def one_sided_sphere(tmp_path: Path) -> TrainedModel:
    """Discs on a sphere, seen from outside by five views each (so one-sided culling
    hides the far half), with view-dependent colour (SH degree 3) and an env map."""
    base = sphere_model(4000)
    params = dict(base.params)
    gen = torch.Generator().manual_seed(1)
    params["sh_rest"] = 0.2 * torch.randn(params["sh_rest"].shape, generator=gen)
    g = Gaussians(params, sh_degree=3)
    seen_from_outside(g)
    env = EnvMap(16)
    env.set_texels(default_env(texel_directions(16)))
    cfg = TrainConfig(envmap_resolution=16)
    extra = {"iteration": cfg.iterations, "config": cfg.model_dump(mode="json"),
             "envmap": env.state_dict()}  # fmt: skip
    path = save_checkpoint(tmp_path / "checkpoint.pt", g, extra)
    return TrainedModel.open(path, device="cpu").freeze()


def test_frozen_frame_without_hidden_gaussians_is_identical(tmp_path: Path) -> None:
    model = one_sided_sphere(tmp_path)
    intr = Intrinsics(60.0, 60.0, 32.0, 24.0, 64, 48)
    channels = ("final", "base", "normal", "depth", "alpha")
    for eye in ([2.2, 0.0, 0.6], [-1.0, 1.8, -0.9]):
        cam = Camera.look_at(eye, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], intr)
        phase = model.phase
        cull = view_opacity_scale(model.gaussians, cam, one_sided=phase.one_sided,
                                  grazing=phase.grazing)  # fmt: skip
        assert cull is not None and 0.3 < float((cull == 0).float().mean()) < 0.7
        fast = model.render(cam, channels)
        ref = model.render(cam, channels, compact=False)
        for ch in channels:
            assert torch.equal(fast.image(ch), ref.image(ch)), ch
        assert float(ref.image("alpha").max()) > 0.9  # the sphere is in view


def test_a_frame_without_depth_leaves_its_two_channels_out_and_nothing_else(
    tmp_path: Path,
) -> None:
    """A frame asked for no ``depth`` composites neither D nor centre z (the viewer's
    shaded frame: 7 channels of 9), and every channel it has is the full frame's, bit
    for bit (each channel composites on its own); asking it for depth says why not."""
    frozen = one_sided_sphere(tmp_path)
    unfrozen = TrainedModel.open(tmp_path / "checkpoint.pt", device="cpu")
    intr = Intrinsics(60.0, 60.0, 32.0, 24.0, 64, 48)
    cam = Camera.look_at([2.2, 0.3, 0.6], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], intr)
    colour = ("final", "specular", "base", "normal", "w_r", "roughness", "alpha")
    for model in (frozen, unfrozen):
        lean = model.render(cam, colour)
        full = model.render(cam, (*colour, "depth"))
        assert lean.gbuffer.plane_dist is None and lean.gbuffer.z_blend is None
        assert full.gbuffer.plane_dist is not None and full.gbuffer.z_blend is not None
        for ch in colour:
            assert torch.equal(lean.image(ch), full.image(ch)), ch
        assert float(lean.image("alpha").max()) > 0.9
        with pytest.raises(ValueError, match="render it with the 'depth' channel"):
            lean.depth()


def test_mesh_fusion_frames_are_the_same_from_a_frozen_copy(tmp_path: Path) -> None:
    """Mesh fusion renders a frozen copy of the model it is given (``frozen``): the
    original stays unfrozen, and every frame it fuses (depth, valid, colour, weight) is
    the unfrozen model's up to float rounding (a frozen model projects precomputed
    covariances instead of building them from rotations and scales)."""
    from core.meshing.mesh import model_depth_frame
    from core.scene.views import View

    one_sided_sphere(tmp_path)
    model = TrainedModel.open(tmp_path / "checkpoint.pt", device="cpu")
    copy = model.frozen()
    assert copy is not model and copy._static is not None and model._static is None
    assert copy.frozen() is copy
    intr = Intrinsics(60.0, 60.0, 32.0, 24.0, 64, 48)
    for eye in ([2.2, 0.0, 0.6], [0.4, -2.0, 1.1]):
        cam = Camera.look_at(eye, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], intr)
        view = View(name="v", camera=cam, image=torch.zeros(48, 64, 3))
        a, b = model_depth_frame(copy, view), model_depth_frame(model, view)
        assert int(a.valid.sum()) > 100
        assert torch.equal(a.empty, b.empty)
        assert float((a.valid != b.valid).float().mean()) < 1e-3  # a threshold may flip
        both = a.valid & b.valid
        torch.testing.assert_close(a.depth[both], b.depth[both], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(a.color[both], b.color[both], rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(a.weight[both], b.weight[both], rtol=1e-5, atol=1e-5)


def test_a_frozen_frame_in_plane_order_takes_no_eigenvalues(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Plane order needs each splat's reach (3 × its largest scale): a frozen model
    keeps it from its scales, as the live model computes it, instead of taking the
    eigenvalues of every covariance each frame (~0.1 s at 134k splats); the frames
    match the live model's."""
    one_sided_sphere(tmp_path)
    live = TrainedModel.open(tmp_path / "checkpoint.pt", device="cpu")
    frozen = live.frozen()
    assert live.phase.splat_order == "auto"  # plane order on the cpu backend
    cam = Camera.look_at([2.2, 0.0, 0.6], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0],
                         Intrinsics(60.0, 60.0, 32.0, 24.0, 64, 48))  # fmt: skip
    expected = live.render(cam, ("base", "normal", "alpha"))

    def refuse(*_args, **_kwargs):
        raise AssertionError("a frozen frame decomposed its covariances")

    monkeypatch.setattr(torch.linalg, "eigvalsh", refuse)
    monkeypatch.setattr(torch.linalg, "eigh", refuse)
    got = frozen.render(cam, ("base", "normal", "alpha"))
    for ch in ("base", "normal", "alpha"):
        torch.testing.assert_close(got.image(ch), expected.image(ch), rtol=1e-5, atol=1e-5)
