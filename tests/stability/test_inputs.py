"""Bad and degenerate inputs: a clear error naming file and field, or a stated behaviour.

Expected answers:

* NaN / ±Inf anywhere in a pose or an intrinsic, in any of the five formats →
  ``SceneError`` whose ``file`` is the metadata file and whose ``field`` names the frame,
  image, row or key;
* NaN / ±Inf in an image's colour or alpha channel, or NaN in a separate mask file →
  ``SceneError`` naming that image/mask file (before the fix alpha and mask files were
  clamped, and clamp keeps NaN: the training targets became NaN); ±Inf in a mask file
  is clipped to 1 / 0 as the file is read (a defined value);
* one training view: trains without the multi-view loss, and the plan says why (no
  neighbour); all cameras identical: no neighbours (no parallax), same; all cameras on one
  line looking the same way: finite bounds from the fallback, neighbours along the line;
* views whose masks are empty: zero valid pixels there, single- and multi-view losses
  exactly 0 with finite gradients, and a run whose masks are all empty still trains
  (random initialisation in the bounds: the visual hull has nothing to carve from).
"""

from __future__ import annotations

import json
import math
import pickle
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core.config import config_from_dict
from core.errors import SceneError
from core.scene.cameras import Camera
from core.scene.formats import load_scene
from core.scene.formats.writers import write_blender, write_scene
from core.scene.imageio import write_image
from core.scene.synthetic import make_scene
from core.scene.views import View
from core.training.losses import multi_view_loss, single_view_loss
from core.training.trainer import Trainer
from tests.stability.common import BACKENDS, TINY_TRAIN, all_finite, replace_views

BAD = [float("nan"), float("inf"), float("-inf")]


@pytest.fixture(scope="module")
def small_scene():
    return make_scene("sphere", "glossy", n_train=3, n_test=1, size=8, seed=4, samples=1)


def _edit_json(path: Path, fn: Callable[[dict], None]) -> None:
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc))  # NaN / Infinity tokens, which json.loads accepts


def _corrupt(fmt: str, root: Path, where: int, which: int, bad: float) -> tuple[str, str]:
    """Put ``bad`` into one number of the metadata; returns (file name, field fragment)."""
    if fmt in ("blender", "nerfstudio"):
        name = "transforms_train.json" if fmt == "blender" else "transforms.json"
        path = root / name
        doc = json.loads(path.read_text())
        i = where % len(doc["frames"])
        if which == 12:  # an intrinsic
            key = "camera_angle_x" if fmt == "blender" else "fl_x"
            if fmt == "blender":
                doc[key] = bad
                path.write_text(json.dumps(doc))
                return name, key
            doc["frames"][i][key] = bad
            path.write_text(json.dumps(doc))
            return name, f"frames[{i}].{key}"
        doc["frames"][i]["transform_matrix"][which // 4][which % 4] = bad
        path.write_text(json.dumps(doc))
        return name, f"frames[{i}].transform_matrix"
    if fmt == "colmap":
        if which == 12:
            path = root / "sparse" / "0" / "cameras.txt"
            lines = path.read_text().splitlines()
            k = next(j for j, s in enumerate(lines) if s and not s.startswith("#"))
            parts = lines[k].split()
            parts[4] = repr(bad)  # fx
            lines[k] = " ".join(parts)
            path.write_text("\n".join(lines) + "\n")
            return "cameras.txt", "camera"
        path = root / "sparse" / "0" / "images.txt"
        lines = path.read_text().splitlines()
        data = [j for j, s in enumerate(lines) if s and not s.startswith("#")]
        k = data[where % len(data)]
        parts = lines[k].split()
        parts[1 + which % 7] = repr(bad)  # QW..TZ
        lines[k] = " ".join(parts)
        path.write_text("\n".join(lines) + "\n")
        return "images.txt", "image"
    if fmt == "llff":
        path = root / "poses_bounds.npy"
        arr = np.load(path)
        i = where % arr.shape[0]
        arr[i, 4 if which == 12 else which] = bad  # column 4 is the height of hwf
        np.save(path, arr)
        return "poses_bounds.npy", f"row {i}"
    if fmt == "nero":
        paths = sorted(root.glob("*-camera.pkl"))
        path = paths[where % len(paths)]
        pose, K = pickle.loads(path.read_bytes())
        if which == 12:
            K = K.copy()
            K[0, 0] = bad
            field = "K"
        else:
            pose = pose.copy()
            pose[which // 4, which % 4] = bad
            field = "pose"
        path.write_bytes(pickle.dumps((pose, K)))
        return path.name, field
    raise AssertionError(fmt)


@settings(
    max_examples=30,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    fmt=st.sampled_from(["blender", "nerfstudio", "colmap", "llff", "nero"]),
    where=st.integers(0, 3),
    which=st.integers(0, 12),  # 0..11: a pose entry (3×4), 12: an intrinsic
    bad=st.sampled_from(BAD),
)
def test_non_finite_metadata_names_file_and_field(small_scene, fmt, where, which, bad):
    """Any pose or intrinsic set to NaN/±Inf → SceneError(file=<metadata>, field=<entry>)."""
    with tempfile.TemporaryDirectory() as d:
        root = write_scene(small_scene, Path(d) / fmt, fmt)
        fname, field = _corrupt(fmt, root, where, which, bad)
        with pytest.raises(SceneError) as err:
            load_scene(root, format=fmt)
        e = err.value
        assert e.file is not None and Path(e.file).name == fname, (str(e), fname)
        assert e.field is not None and field in e.field, (str(e), field)


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("part", ["rgb", "alpha", "mask_file"])
def test_non_finite_pixels_name_the_image_file(small_scene, tmp_path, bad, part):
    """A NaN/Inf value in an EXR's colour or alpha, or NaN in an EXR mask file →
    SceneError naming that file (training targets would otherwise be NaN); ±Inf in a
    mask file reads as 1 / 0."""
    root = write_blender(small_scene, tmp_path / "scene")
    view = small_scene.train[0]
    png = root / "train" / "r_0.png"
    png.unlink()
    rgb = view.image.clone()
    alpha = view.mask.clone()
    if part == "rgb":
        rgb[2, 3, 0] = bad
    elif part == "alpha":
        alpha[2, 3] = bad
    exr = write_image(root / "train" / "r_0.exr", rgb, alpha=alpha if part != "mask_file" else None)
    culprit = exr
    if part == "alpha":
        # write_image clips alpha to [0, 1]; put the bad value in with a raw write
        import OpenImageIO as oiio

        buf = np.concatenate([rgb.numpy(), alpha.numpy()[..., None]], axis=2).astype(np.float32)
        spec = oiio.ImageSpec(buf.shape[1], buf.shape[0], 4, oiio.FLOAT)
        spec.alpha_channel = 3
        out = oiio.ImageOutput.create(str(exr))
        assert out.open(str(exr), spec) and out.write_image(buf)
        out.close()
    if part == "mask_file":
        m = alpha.clone()
        m[2, 3] = bad
        culprit = tmp_path / "scene" / "train" / "r_0_mask.exr"
        write_image(culprit, m[..., None].expand(-1, -1, 3).contiguous(), encode_srgb=False)
        _edit_json(
            root / "transforms_train.json",
            lambda d: d["frames"][0].__setitem__("mask_path", "./train/r_0_mask.exr"),
        )
    if part == "mask_file" and not math.isnan(bad):
        # mask files are clipped to [0, 1] as they are read: ±Inf is a defined 1 / 0
        mask = load_scene(root).train[0].mask
        assert all_finite(mask) and float(mask[2, 3]) == (1.0 if bad > 0 else 0.0)
        return
    with pytest.raises(SceneError) as err:
        load_scene(root)
    assert err.value.file is not None and Path(err.value.file).name == culprit.name, str(err.value)
    assert "NaN" in str(err.value) or "Inf" in str(err.value)


def _short_run(scene, out: Path, iterations: int = 15) -> Trainer:
    cfg = config_from_dict({**TINY_TRAIN, "iterations": iterations, "backend": BACKENDS[-1]})
    t = Trainer(scene, cfg, out)
    t.setup(resume=False)
    t.train()
    assert all(all_finite(p) for p in t.gaussians.params.values())
    return t


def test_single_view_scene_trains_without_multi_view(sphere_48, tmp_path):
    """One view: the plan switches the multi-view loss off and says why; training runs."""
    scene = replace_views(sphere_48, sphere_48.train[:1])
    t = _short_run(scene, tmp_path)
    mv = t.plan.multi_view
    assert mv.value is False and "neighbour" in mv.reason, mv.reason
    assert mv.evidence["views"] == 1 and mv.evidence["views_with_neighbour"] == 0
    assert t.plan.neighbours == [None]


def test_identical_cameras_have_no_neighbours(sphere_48, tmp_path):
    """Six copies of one view: no parallax, so no view is another's neighbour; the
    camera-only bounds fall back to a finite centre and radius; training runs."""
    from core.scene.views import bounds_from_cameras

    v = sphere_48.train[0]
    scene = replace_views(
        sphere_48, [View(v.camera, v.image, v.mask, f"copy{i}") for i in range(6)]
    )
    centre, radius = bounds_from_cameras([x.camera for x in scene.train])
    assert all_finite(centre) and math.isfinite(radius) and radius > 0
    t = _short_run(scene, tmp_path)
    assert t.plan.neighbours == [None] * 6 and t.plan.multi_view.value is False


def test_colinear_cameras(sphere_48, tmp_path):
    """Five cameras on one line, all looking along it (a dolly shot at the sphere): the
    axes give no triangulation, so the bounds fall back to a finite point ahead; each
    camera's neighbour is another on the line (same axis, non-zero baseline)."""
    from core.scene.views import bounds_from_cameras

    base = sphere_48.train[0]
    views = []
    for i in range(5):
        w2c = base.camera.world_to_cam.clone()
        w2c[2, 3] -= 0.1 * i  # move back along the optical axis
        views.append(View(Camera(base.camera.intrinsics, w2c, f"dolly{i}"), base.image, base.mask))
    centre, radius = bounds_from_cameras([v.camera for v in views])
    assert all_finite(centre) and math.isfinite(radius) and radius > 0
    scene = replace_views(sphere_48, views)
    t = _short_run(scene, tmp_path)
    assert all(j is not None and j != i for i, j in enumerate(t.plan.neighbours))


def test_empty_masks_give_zero_valid_pixels_and_finite_losses(sphere_48):
    """An all-zero mask leaves no valid pixel: both geometric losses are exactly 0 with a
    finite (zero) gradient."""
    v, nb = sphere_48.train[0], sphere_48.train[1]
    depth = torch.full((24, 24), 3.0, requires_grad=True)
    normal = torch.randn(24, 24, 3, requires_grad=True)
    valid = torch.ones(24, 24, dtype=torch.bool) & (torch.zeros(24, 24) > 0.5)  # mask empty
    sv = single_view_loss(normal, depth, valid, v.camera)
    mv, stats = multi_view_loss(depth, valid, v.camera, depth.detach(), valid, nb.camera)
    assert float(sv.detach()) == 0.0 and float(mv.detach()) == 0.0 and stats["pixels"] == 0.0
    (sv + mv).backward()
    assert all_finite(depth.grad, normal.grad)


@pytest.mark.parametrize("which", ["some", "all"])
def test_runs_with_empty_masks(sphere_48, tmp_path, which):
    """Every other view's mask empty, or all of them: the run finishes finite (with all
    masks empty the targets are plain background and init is random in the bounds)."""

    def empty(v: View) -> View:
        return View(v.camera, v.image, torch.zeros_like(v.mask), v.name)

    train = [empty(v) if (which == "all" or i % 2) else v for i, v in enumerate(sphere_48.train)]
    t = _short_run(replace_views(sphere_48, train), tmp_path)
    if which == "all":
        assert t.plan.init["method"] == "random in bounds", t.plan.init
