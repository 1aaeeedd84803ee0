"""Structure from motion (issue 23): known cameras recovered from a generated textured
capture, the failure cases named, pair selection and alignment on their own."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from core.cli import main
from core.errors import SceneError
from core.scene.formats import load_scene
from core.scene.imageio import write_image
from core.scene.sfm import SfmCancelledError, SfmError, SfmOptions, run_sfm
from core.scene.sfm.align import pose_errors, umeyama
from core.scene.sfm.matching import choose_strategy
from core.scene.sfm.pairs import (
    EXHAUSTIVE_MAX_IMAGES,
    exhaustive_pairs,
    fit_vocabulary,
    pairs_with,
    retrieval_pairs,
    similarity,
)
from core.scene.textured import cell_texture, render_textured_view, ring_cameras

# Issue 23's goal for real captures, held on a clean synthetic one.
MAX_ROTATION_DEG = 0.25
MAX_CENTRE_REL = 0.0025


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, np.ndarray]]:
    """32 photos of a textured sphere in a textured room, as a phone leaves them: JPEG
    with an EXIF orientation tag, non-square (192x144), every 8th photo at another
    size (256x192: a second camera group), with PNG object masks."""
    import OpenImageIO as oiio

    folder = tmp_path_factory.mktemp("capture")
    truth = {}
    for k, cam in enumerate(ring_cameras(32, 192, 144)):
        if k % 8 == 7:
            cam = replace(cam, intrinsics=cam.intrinsics.scaled(4 / 3))
        rgb, mask = render_textured_view(cam)
        png = write_image(folder / f"{cam.name}.png", rgb)
        buf = oiio.ImageBuf(str(png))
        buf.specmod().attribute("Orientation", 6)  # "rotate 90° to view": pixels as stored
        buf.specmod().attribute("Compression", "jpeg:95")
        (folder / "images").mkdir(exist_ok=True)
        assert buf.write(str(folder / "images" / f"{cam.name}.jpg"))
        png.unlink()
        write_image(folder / "masks" / f"{cam.name}.png", mask, encode_srgb=False)
        truth[cam.name] = cam.world_to_cam.numpy()
    return folder, truth


def unrelated_photos(folder: Path, n: int, size: tuple[int, int] = (192, 144)) -> list[str]:
    """``n`` photos of unrelated flat textures, each rotated, scaled and shifted at random
    (so that no two of them share a feature layout)."""
    folder.mkdir(parents=True, exist_ok=True)
    w, h = size
    v, u = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
    names = []
    for k in range(n):
        g = torch.Generator().manual_seed(100 + k)
        a, s, o = torch.rand(3, generator=g) * torch.tensor([math.pi, 0.05, 50.0])
        c, si = math.cos(a), math.sin(a)
        p = torch.stack([c * u - si * v + o, si * u + c * v, torch.full_like(u, float(k))], -1)
        name = f"stray_{k}.png"
        write_image(folder / name, cell_texture(p * (0.12 + s), 1.0, 100 + k))
        names.append(name)
    return names


def test_sfm_recovers_known_cameras(capture: tuple[Path, dict], tmp_path: Path) -> None:
    folder, truth = capture
    events: list[dict] = []
    res = run_sfm(
        folder / "images", tmp_path / "scene", masks=folder / "masks", on_event=events.append
    )
    r = res.report
    assert (r["registered"], r["images"], r["unregistered"]) == (32, 32, [])
    assert r["matching"]["strategy"] == "exhaustive"  # 32 <= 40
    small, large = sorted((c["width"], c["height"]) for c in r["cameras"])  # two groups
    assert large[0] / small[0] == pytest.approx(4 / 3, rel=0.03), r["cameras"]
    scene = load_scene(tmp_path / "scene", test_every=0)
    assert scene.format == "colmap" and len(scene.views) == 32 and scene.has_masks
    got = {v.name: v.camera.world_to_cam.numpy() for v in scene.views}
    err = pose_errors(got, truth)
    s = err.summary()
    assert s["rotation_deg_median"] <= MAX_ROTATION_DEG, s
    assert s["center_rel_median"] <= MAX_CENTRE_REL, s
    # the masks went through the same undistortion as their images and still cover
    # the object: the sphere's projection under the true camera
    for v in scene.views:
        assert v.mask is not None and v.mask.shape == v.image.shape[:2]
    # with masks the point cloud keeps the object (radius 0.6), not the room (radius 6);
    # its size follows the focal length, which a ring of cameras pins down to a few %
    radius = np.linalg.norm(err.similarity.apply(scene.points.double().numpy()), axis=1)
    assert np.quantile(np.abs(radius - 0.6), 0.9) < 0.06, np.quantile(radius, [0.1, 0.5, 0.9])
    # progress: every stage in order, steps within their totals, a closing event
    stages = [e["stage"] for e in events if e["type"] == "sfm_stage"]
    assert stages == ["features", "matching", "mapping", "undistort"]
    steps = [e for e in events if e["type"] == "sfm"]
    assert steps and all(0 < e["done"] <= e["total"] for e in steps)
    assert events[-1]["type"] == "sfm_done" and events[-1]["report"]["registered"] == 32
    saved = json.loads((tmp_path / "scene" / "sfm_report.json").read_text())
    assert saved["registered"] == 32 and saved["peak_rss_mb"] > 0
    assert "registered 32 of 32 images" in (tmp_path / "scene" / "sfm_report.txt").read_text()
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]  # no temporary folder left


def test_unregistered_images_are_named_and_nothing_is_written(
    capture: tuple[Path, dict], tmp_path: Path
) -> None:
    photos = tmp_path / "photos"
    shutil.copytree(capture[0] / "images", photos)
    stray = unrelated_photos(photos, 8)
    before = {p.name: p.stat().st_mtime_ns for p in photos.iterdir()}
    with pytest.raises(SfmError) as info:
        run_sfm(photos, tmp_path / "scene", options=SfmOptions(min_registered=0.9))
    err = info.value
    assert err.report is not None
    registered = err.report["registered"]
    # Every stray is left out and named. The mapper does not register every real view on
    # every run (a CI run left one of the 32 out); one it leaves out is named as well.
    assert set(stray) <= set(err.unregistered) and 30 <= registered <= 32
    assert len(err.unregistered) == 40 - registered
    assert f"registered {registered} of 40 images" in str(err)
    assert all(n in str(err) for n in err.unregistered)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]  # no scene, no temp
    assert {p.name: p.stat().st_mtime_ns for p in photos.iterdir()} == before


def test_too_few_images(tmp_path: Path) -> None:
    unrelated_photos(tmp_path / "photos", 2)
    with pytest.raises(SfmError, match=r"at least 3 images.*holds 2"):
        run_sfm(tmp_path / "photos", tmp_path / "scene")
    assert not (tmp_path / "scene").exists()


def test_no_overlap(tmp_path: Path) -> None:
    unrelated_photos(tmp_path / "photos", 4)
    with pytest.raises(SfmError, match="no overlap") as info:
        run_sfm(tmp_path / "photos", tmp_path / "scene")
    assert sorted(info.value.unregistered) == [f"stray_{k}.png" for k in range(4)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]


def test_bad_inputs_name_the_file(tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    unrelated_photos(photos, 3)
    (photos / "broken.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(SceneError, match="cannot read image") as info:
        run_sfm(photos, tmp_path / "scene")
    assert info.value.file == str(photos / "broken.jpg")
    (photos / "broken.jpg").unlink()
    masks = tmp_path / "masks"
    unrelated_photos(masks, 2)  # stray_0, stray_1: stray_2 has none
    with pytest.raises(SceneError, match=r"no mask for image stray_2\.png"):
        run_sfm(photos, tmp_path / "scene", masks=masks)
    with pytest.raises(SfmError, match="feature masks need a mask folder"):
        run_sfm(photos, tmp_path / "scene", options=SfmOptions(feature_masks=True))
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    with pytest.raises(SfmError, match="is not empty"):
        run_sfm(photos, tmp_path / "full")
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"


def test_cancel_leaves_nothing(tmp_path: Path) -> None:
    """``should_stop`` turning true mid-run ends it with SfmCancelledError, no scene."""
    unrelated_photos(tmp_path / "photos", 20)
    events: list[dict] = []
    with pytest.raises(SfmCancelledError, match="cancelled during features"):
        run_sfm(
            tmp_path / "photos",
            tmp_path / "scene",
            on_event=events.append,
            should_stop=lambda: any(e["type"] == "sfm" for e in events),
        )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]


def test_cli_reports_the_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    unrelated_photos(tmp_path / "photos", 2)
    code = main(["sfm", str(tmp_path / "photos"), "--out", str(tmp_path / "scene"), "--quiet"])
    assert code == 2
    assert "glint sfm: error: structure from motion needs at least 3 images" in (
        capsys.readouterr().err
    )


def test_pycolmap_comes_after_openimageio(tmp_path: Path) -> None:
    """Taking pycolmap through Glint keeps PNG writing alive in a fresh process (pycolmap
    imported first breaks OpenImageIO's PNG writer: core/scene/sfm/colmap_lib.py)."""
    code = (
        "import numpy as np\n"
        "from core.scene.sfm.colmap_lib import pycolmap\n"
        "from core.scene.imageio import write_image\n"
        f"for k in range(3): write_image({str(tmp_path)!r} + f'/m{{k}}.png', np.zeros((8, 8)))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert len(list(tmp_path.glob("m*.png"))) == 3


# -- pair selection ------------------------------------------------------------------------


def test_matching_strategy_by_image_count() -> None:
    assert choose_strategy(EXHAUSTIVE_MAX_IMAGES) == "exhaustive"
    assert choose_strategy(EXHAUSTIVE_MAX_IMAGES + 1) == "retrieval"
    assert choose_strategy(500, "exhaustive") == "exhaustive"
    with pytest.raises(ValueError, match="unknown matching"):
        choose_strategy(10, "vocab")
    assert len(exhaustive_pairs(7)) == 21


def test_retrieval_finds_the_images_that_share_features() -> None:
    """Three groups of images, each drawing its descriptors from its own pool: every
    image's retrieved neighbours are its own group's images."""
    rng = np.random.default_rng(0)
    groups, per_group = 3, 6
    desc, group_of = [], []
    for g in range(groups):
        pool = rng.random((300, 128)) * (rng.random((300, 128)) < 0.15)  # sparse, like SIFT
        for _ in range(per_group):
            pick = pool[rng.choice(300, 150, replace=False)]
            desc.append(
                np.clip(255 * (pick + 0.02 * rng.random(pick.shape)), 0, 255).astype(np.uint8)
            )
            group_of.append(g)
    sim = similarity(desc, fit_vocabulary(desc, words=64))
    pairs = retrieval_pairs(sim, neighbours=per_group - 1, window=0)
    assert pairs and all(group_of[i] == group_of[j] for i, j in pairs)
    assert len(pairs) == groups * per_group * (per_group - 1) // 2  # every in-group pair
    # order neighbours come on top; the pairs an unregistered image still needs
    assert (0, 1) in retrieval_pairs(sim, neighbours=0, window=1)
    assert pairs_with([0], 4, {(0, 1)}) == [(0, 2), (0, 3)]
    # over budget, a left-out image gets its most similar images: its own group's
    few = pairs_with([0, 6], len(desc), set(), sim=sim, budget=6)
    assert len(few) == 6 and all(group_of[i] == group_of[j] for i, j in few)


# -- alignment -----------------------------------------------------------------------------


def _rotation(axis: np.ndarray, deg: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(deg)
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def test_umeyama_recovers_a_similarity() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    R = _rotation(np.array([1.0, 2.0, -0.5]), 73.0)
    dst = 2.5 * src @ R.T + np.array([1.0, -3.0, 0.25])
    sim = umeyama(src, dst)
    assert sim.scale == pytest.approx(2.5, abs=1e-9)
    np.testing.assert_allclose(sim.R, R, atol=1e-9)
    np.testing.assert_allclose(sim.apply(src), dst, atol=1e-9)
    mirrored = src * np.array([1.0, 1.0, -1.0])  # no rotation maps it: still a rotation back
    assert np.linalg.det(umeyama(src, mirrored).R) == pytest.approx(1.0)


def test_pose_errors_after_a_similarity() -> None:
    rng = np.random.default_rng(2)
    truth, recovered = {}, {}
    S, t = _rotation(np.array([0.3, -1.0, 0.2]), 40.0), np.array([0.5, 0.1, -2.0])
    for k in range(8):
        w2c = np.eye(4)
        w2c[:3, :3] = _rotation(rng.normal(size=3), float(rng.uniform(0, 180)))
        w2c[:3, 3] = rng.normal(size=3) * 3
        truth[f"v{k}"] = w2c
        # the same camera in a frame x' = (Sᵀ(x − t)) / 0.5: poses up to a similarity
        rec = np.eye(4)
        rec[:3, :3] = w2c[:3, :3] @ S
        rec[:3, 3] = (w2c[:3, :3] @ t + w2c[:3, 3]) / 0.5
        recovered[f"v{k}"] = rec
    v3 = recovered["v3"]  # turn camera v3 by 1 degree about its centre
    centre = -v3[:3, :3].T @ v3[:3, 3]
    v3[:3, :3] = _rotation(np.array([0.0, 0.0, 1.0]), 1.0) @ v3[:3, :3]
    v3[:3, 3] = -v3[:3, :3] @ centre
    err = pose_errors(recovered, truth)
    assert err.rotation_deg[err.names.index("v3")] == pytest.approx(1.0, abs=1e-6)
    assert np.median(err.rotation_deg) < 1e-6 and err.center_rel.max() < 1e-9
    assert err.similarity.scale == pytest.approx(0.5)
