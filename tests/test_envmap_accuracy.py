"""The env-map score: learned lighting against the scene's true map (issue 21)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from core.evaluation.envmap_accuracy import (
    compare_envmaps,
    exposure_fit,
    load_true_envmap,
    reflected_directions,
    save_envmap_comparison,
    seen_fraction,
)
from core.evaluation.geometry import chamfer_floor_x100
from core.render.envmap import EnvMap, texel_directions
from core.scene.formats import load_scene
from core.scene.synthetic import default_env, write_synthetic_scene
from core.scene.views import Scene

RES = 16


@pytest.fixture(scope="module")
def mirror(tmp_path_factory) -> tuple[Path, Scene]:
    root = write_synthetic_scene(
        tmp_path_factory.mktemp("env") / "s", "sphere", "mirror", n_train=12, n_test=2,
        size=32, ground_truth=True,
    )  # fmt: skip
    return root, load_scene(root)


def envmap_of(fn, scale: float = 1.0) -> EnvMap:
    env = EnvMap(RES)
    env.set_texels(scale * fn(texel_directions(RES)))
    return env


def test_the_written_map_is_the_scene_environment(mirror) -> None:
    root, _ = mirror
    truth = load_true_envmap(root)
    assert truth is not None
    d = torch.nn.functional.normalize(
        torch.randn(500, 3, generator=torch.Generator().manual_seed(1)), dim=-1
    )
    err = (truth.sample(d) - default_env(d)).abs()
    # bilinear lookup of a 256x128 map of a smooth function (the sun lobe is sharpest)
    assert float(err.median()) < 0.01 and float(err.max()) < 0.5


def test_mirror_views_reflect_most_of_the_sphere(mirror) -> None:
    root, scene = mirror
    dirs, source = reflected_directions(scene.train, root)
    assert source == "gt"
    assert len(dirs) > 1000
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(len(dirs)), atol=1e-4)
    assert seen_fraction(dirs) > 0.75


def test_seen_fraction_of_one_hemisphere_is_a_half() -> None:
    d = torch.nn.functional.normalize(
        torch.randn(200_000, 3, generator=torch.Generator().manual_seed(0)), dim=-1
    )
    up = d[d[:, 2] > 0]
    assert seen_fraction(up) == pytest.approx(0.5, abs=0.03)
    assert seen_fraction(d) == pytest.approx(1.0, abs=0.01)
    assert seen_fraction(torch.zeros(0, 3)) == 0.0


def test_the_true_map_scores_high_at_any_exposure_and_a_grey_one_low(mirror) -> None:
    root, scene = mirror
    truth = load_true_envmap(root)
    dirs, _ = reflected_directions(scene.train, root)
    right = compare_envmaps(envmap_of(default_env, 0.5), truth, dirs)
    assert right["psnr"] > 30
    assert right["log_correlation"] > 0.98
    assert right["exposure"] == pytest.approx(0.5, rel=0.05)
    assert right["seen_fraction"] > 0.75
    # a tinted map (a coloured metal's reflectance) is only right after per-channel gains
    tint = torch.tensor([1.0, 0.75, 0.35])
    gold = compare_envmaps(envmap_of(lambda d: default_env(d) * tint), truth, dirs)
    assert gold["psnr"] < right["psnr"] - 5
    assert gold["psnr_channel_gains"] > 30
    assert gold["channel_gains"] == pytest.approx(tint.tolist(), rel=0.05)
    grey = compare_envmaps(EnvMap(RES, init_value=0.5), truth, dirs)
    assert grey["psnr"] < right["psnr"] - 12
    # a constant map has no luminance variation to correlate with
    assert not grey["log_correlation"] > 0.5
    flipped = compare_envmaps(envmap_of(lambda d: default_env(-d)), truth, dirs)
    assert flipped["psnr"] < right["psnr"] - 10
    assert flipped["log_correlation"] < 0.5


def test_exposure_fit_ignores_what_the_display_clips() -> None:
    g = torch.Generator().manual_seed(0)
    true = torch.rand(5000, 3, generator=g) ** 3
    true[:200] *= 500.0  # highlights far beyond what any photo keeps
    learned = 2.5 * true
    assert exposure_fit(learned, true) == pytest.approx(2.5, rel=0.02)
    assert exposure_fit(learned, true, 0.2) == pytest.approx(2.5, rel=0.02)
    # where the photos (exposure k) clip, a map can only learn "at least the clip level"
    k = 0.8
    learned = torch.where(true * k > 1.0, torch.full_like(true, 2.5 / k), learned)
    assert exposure_fit(learned, true, k) == pytest.approx(2.5, rel=0.02)
    # a plain least-squares fit in linear radiance would follow the highlights instead
    lsq = float((learned * true).sum() / (true * true).sum())
    assert lsq < 0.1


def test_comparison_picture(mirror, tmp_path: Path) -> None:
    from PIL import Image

    root, scene = mirror
    truth = load_true_envmap(root)
    dirs, _ = reflected_directions(scene.train[:2], root)
    path = save_envmap_comparison(tmp_path / "c.png", envmap_of(default_env), truth, dirs, 1.0)
    img = Image.open(path)
    assert img.size == (256, 2 * 128 + 4)


def test_no_true_map_or_no_learned_map_gives_none(tmp_path: Path) -> None:
    assert load_true_envmap(tmp_path) is None
    assert load_true_envmap(None) is None


def test_chamfer_floor_read_from_meta(tmp_path: Path) -> None:
    meta = {
        "gt": {"chamfer_sampling_floor_x100": {"pred_200k_points": 0.25, "pred_1M_points": 0.18}}
    }
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    assert chamfer_floor_x100(tmp_path, 200_000) == 0.25
    assert chamfer_floor_x100(tmp_path, 1_000_000) == 0.18
    assert chamfer_floor_x100(tmp_path, 500_000) is None
    assert chamfer_floor_x100(tmp_path / "missing", 200_000) is None
    assert math.isfinite(chamfer_floor_x100(tmp_path, 200_000) or math.nan)
