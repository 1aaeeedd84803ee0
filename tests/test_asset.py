"""Relightable assets (glint export --asset): material mapping, irradiance, atlas
texels and tangent frames, the .glb (trimesh and Khronos' glTF-Validator read it), the
training option, the diffuse fallback, bad input and cancellation."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from core.asset.export import (
    ASSET_FILES,
    AssetCancelledError,
    AssetError,
    AssetOptions,
    asset_run,
    export_asset,
)
from core.asset.glb import GLTF_FROM_WORLD
from core.asset.material import (
    fit_metallic_roughness,
    gltf_material,
    irradiance,
    irradiance_sh,
)
from core.asset.texels import fill_unknown, rasterize_atlas
from core.asset.uv_mesh import face_frames, unwrap
from core.config import config_from_dict
from core.errors import GlintError
from core.model.run_folder import open_run
from core.render.envmap import texel_directions
from core.scene.imageio import linear_to_srgb, srgb_to_linear
from core.training.run import train_scene

ROOT = Path(__file__).resolve().parents[1]
VALIDATOR = ROOT / ".tools" / "gltf-validator"
LUMA = np.array([0.2126, 0.7152, 0.0722])
SMALL = {"faces": 1500, "texture_size": 64, "views": 4}


# ---------------------------------------------------------------- material mapping


def test_grey_materials_round_trip() -> None:
    """A glTF material with a grey c (any dielectric, a grey metal) under light I gives
    Eq. 9's base (1 − m)·c·I and w_r = 0.04(1 − m) + m·c; the fit recovers c and m
    with no residual."""
    rng = np.random.default_rng(0)
    g = rng.uniform(0.05, 0.95, 500)
    m = rng.uniform(0.0, 1.0, 500)
    c = np.repeat(g[:, None], 3, 1)
    w_r = 0.04 * (1 - m) + m * g
    color, metal, resid = fit_metallic_roughness((1 - m)[:, None] * c, w_r)
    np.testing.assert_allclose(metal, m, atol=2e-3)
    np.testing.assert_allclose(color, c, atol=5e-3)
    assert resid.max() < 1e-6


def test_exported_material_renders_like_eq9() -> None:
    """Whatever exposure s the export picks, the glTF terms under the exported map s·E
    give back Eq. 9's base and w_r · E for representable materials (head-on views)."""
    rng = np.random.default_rng(2)
    g = rng.uniform(0.05, 0.9, 300)
    m = rng.uniform(0.0, 1.0, 300)
    light = 1.7  # the true map: uniform radiance 1.7, so I = 1.7 everywhere
    base = ((1 - m) * g)[:, None] * light * np.ones(3)
    # the model learned the map 1/0.3 too bright, and w_r 0.3 times the reflectance
    w_r = 0.3 * (0.04 * (1 - m) + m * g)
    sh = irradiance_sh(torch.full((6, 8, 8, 3), light / 0.3))
    up = np.tile([[0.0, 0.0, 1.0]], (300, 1))
    c, mm, _, s = gltf_material(base, w_r, up, None, sh)
    assert 0.1 < s < 1.0  # grey materials fit exactly over a range of exposures near 0.3
    diffuse = (1 - mm)[:, None] * c * (light / 0.3) * s
    f0 = 0.04 * (1 - mm)[:, None] + mm[:, None] * c
    np.testing.assert_allclose(diffuse, base, atol=1e-3)
    np.testing.assert_allclose(f0 * s, np.repeat(w_r[:, None], 3, 1), atol=1e-3)


def test_mirror_reflectance_averaged_over_views_matches() -> None:
    """A colourless mirror learned as w_r = 0.5, seen partly at grazing angles: under the
    exported map s·E the glTF metal's reflectance averaged over the views,
    s · (F0 (1 − κ) + κ), is the model's 0.5 at every texel (Fresnel included)."""
    n = 400
    kappa = np.random.default_rng(3).uniform(0.0, 0.3, n)
    sh = irradiance_sh(torch.ones(6, 8, 8, 3))
    up = np.tile([[0.0, 0.0, 1.0]], (n, 1))
    c, m, _, s = gltf_material(np.zeros((n, 3)), np.full(n, 0.5), up, None, sh, kappa)
    f0 = 0.04 * (1 - m)[:, None] + m[:, None] * c
    np.testing.assert_allclose(s * (f0 * (1 - kappa[:, None]) + kappa[:, None]), 0.5, atol=2e-3)
    assert np.all(m > 0.95)  # a metal: no diffuse part for a black base


def test_fit_is_the_least_squares_optimum() -> None:
    """For coloured targets (a gold-like base with a strong colourless reflection) no
    (c, m) does better than the fit: not m on a fine grid with random c, nor the fit's m
    with its c perturbed."""
    rng = np.random.default_rng(1)
    a = rng.uniform(0.0, 0.6, (200, 3)) * np.array([1.0, 0.6, 0.1])
    w = rng.uniform(0.0, 0.9, 200)[:, None]
    c, m, e = fit_metallic_roughness(a, w[:, 0])

    def err(mm: np.ndarray, cc: np.ndarray) -> np.ndarray:
        one = 1 - mm
        return np.sum((one * cc - a) ** 2 + (0.04 * one + mm * cc - w) ** 2, 1)

    np.testing.assert_allclose(err(m[:, None], c), e, rtol=1e-9, atol=1e-12)
    for mg in np.linspace(0, 1, 201):
        assert np.all(e <= err(np.full((200, 1), mg), rng.uniform(0, 1, (200, 3))) + 1e-9)
    for _ in range(50):
        near = np.clip(c + rng.normal(0, 0.05, c.shape), 0, 1)
        assert np.all(e <= err(m[:, None], near) + 1e-9)
    assert np.mean(m > 0.5) > 0.2 and np.mean(m < 0.5) > 0.2  # both regimes exercised


def test_metallic_limits() -> None:
    # a coloured base with a dielectric's reflection: metallic 0, the base is the colour
    c, m, _ = fit_metallic_roughness(np.array([[0.5, 0.2, 0.1]]), np.array([0.04]))
    assert m[0] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(c[0], [0.5, 0.2, 0.1], atol=1e-6)
    # a black base with a strong reflection is a grey metal of that reflectance
    c, m, _ = fit_metallic_roughness(np.zeros((1, 3)), np.array([0.7]))
    assert m[0] == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(c[0], [0.7, 0.7, 0.7], atol=1e-6)


def test_diffuse_plan_keeps_the_base_as_colour() -> None:
    base = np.array([[0.2, 0.5, 0.9], [1.5, 0.1, 0.0]])
    color, metal, _, s = gltf_material(base, np.array([0.5, 0.5]), np.eye(3)[:2], None, None)
    assert s == 1.0
    np.testing.assert_allclose(color, np.clip(base, 0, 1))
    assert np.all(metal == 0)


def test_occlusion_divides_the_base() -> None:
    """Under the same light, a texel with AO 0.5 needs twice the albedo for the same base."""
    sh = irradiance_sh(torch.ones(6, 4, 4, 3))
    base = np.full((2, 3), 0.2)
    color, _, _, _ = gltf_material(base, np.full(2, 0.04), np.eye(3)[:2], np.array([1, 0.5]), sh)
    np.testing.assert_allclose(color[1], 2 * color[0], rtol=1e-6)


def test_irradiance_of_uniform_and_half_sky() -> None:
    """Uniform radiance L: Irr = L at every normal. Sky (z > 0) of radiance 1: Irr(+z) =
    1, Irr(−z) = 0, Irr(horizontal) = 1/2 (to the l ≤ 2 truncation's ~6%)."""
    L = torch.tensor([0.3, 0.5, 2.0])
    sh = irradiance_sh(L.expand(6, 16, 16, 3).clone())
    n = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, -0.6, 0.8]])
    np.testing.assert_allclose(irradiance(sh, n), np.tile(L.numpy(), (3, 1)), rtol=1e-3)
    dirs = texel_directions(32, torch.float64, "cpu")
    sky = (dirs[..., 2] > 0).to(torch.float32)[..., None].expand(-1, -1, -1, 3)
    sh = irradiance_sh(sky.contiguous())
    got = irradiance(sh, np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]]))[:, 0]
    np.testing.assert_allclose(got, [1.0, 0.0, 0.5], atol=0.07)


# ---------------------------------------------------------------- atlas and frames


@pytest.fixture(scope="module")
def sphere_atlas():  # type: ignore[no-untyped-def]
    mesh = trimesh.creation.icosphere(subdivisions=3)
    uvm = unwrap(mesh, 128)
    return uvm, rasterize_atlas(uvm, 128)


def test_atlas_texels_lie_on_the_surface(sphere_atlas) -> None:  # type: ignore[no-untyped-def]
    uvm, tex = sphere_atlas
    assert np.all(uvm.uvs >= 0) and np.all(uvm.uvs <= 1)
    assert tex.count > 0.3 * 128 * 128  # xatlas packs densely
    r = np.linalg.norm(tex.points, axis=1)
    assert np.all(r <= 1 + 1e-5) and np.all(r > 0.97)  # on the flat facets of a unit sphere
    # interpolated normals of a sphere point outwards along the position
    cos = np.sum(tex.normals * tex.points / r[:, None], 1)
    assert np.all(cos > 0.99)
    # every texel is claimed once, and the texel's face contains its point
    assert len(set(zip(tex.rows.tolist(), tex.cols.tolist(), strict=True))) == tex.count


def test_tangent_frame_follows_the_uv_directions(sphere_atlas) -> None:  # type: ignore[no-untyped-def]
    """The tangent points along +u and the bitangent along −v (up in the image), as
    glTF's normal textures expect; both are unit and orthogonal to the normal."""
    uvm, tex = sphere_atlas
    dpdu, dpdup = face_frames(uvm.positions, uvm.uvs, uvm.faces)
    du = dpdu[tex.face] / np.linalg.norm(dpdu[tex.face], axis=1, keepdims=True)
    dv = dpdup[tex.face] / np.linalg.norm(dpdup[tex.face], axis=1, keepdims=True)
    assert np.mean(np.sum(tex.tangents * du, 1) > 0.7) > 0.98
    assert np.mean(np.sum(tex.bitangents * dv, 1) > 0.7) > 0.98
    np.testing.assert_allclose(np.linalg.norm(tex.tangents, axis=1), 1, atol=1e-4)
    assert np.abs(np.sum(tex.tangents * tex.normals, 1)).max() < 1e-4
    # a reversed tangent (mirrored chart) would show up as w = -1 where dP/du flips
    assert set(np.unique(uvm.tangents[:, 3])) <= {-1.0, 1.0}


def test_fill_unknown_spreads_into_gutters() -> None:
    img = np.zeros((8, 8, 1), dtype=np.float32)
    known = np.zeros((8, 8), dtype=bool)
    img[3:5, 3:5] = 0.8
    known[3:5, 3:5] = True
    out = fill_unknown(img, known, iterations=2)
    assert np.all(out[3:5, 3:5] == 0.8)
    assert out[1, 1, 0] == pytest.approx(0.8) and out[0, 0, 0] == pytest.approx(0.8)


# ---------------------------------------------------------------- a trained run


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny glossy run trained with outputs.asset on (the training path)."""
    from core.scene.synthetic import write_synthetic_scene

    root = tmp_path_factory.mktemp("asset")
    scene = write_synthetic_scene(root / "scene", "sphere", "glossy", n_train=8, n_test=1, size=32)
    cfg = config_from_dict(
        {"iterations": 40, "init_points": 800, "envmap_resolution": 8,
         "densify": {"enabled": False},
         "outputs": {"mesh": False, "mesh_resolution": 48, "asset": True, "asset_faces": 1500,
                     "asset_texture_size": 64}}
    )  # fmt: skip
    _, summary = train_scene(scene, root / "run", cfg)
    assert summary is not None and "files" in summary["asset"], summary
    return root / "run"


def test_training_writes_the_asset(run: Path) -> None:
    for name in ASSET_FILES:
        assert (run / name).is_file(), name
    info = json.loads((run / "asset.json").read_text())
    assert info["mesh"]["faces"] <= 1500 * 1.05
    assert info["textures"]["size"] == 64 and info["environment"]["present"]
    assert "Relightable asset" in (run / "report.md").read_text()


def test_glb_loads_with_material_uvs_and_y_up(run: Path) -> None:
    scene = trimesh.load(run / "asset.glb", process=False)
    mesh = next(iter(scene.geometry.values()))
    assert mesh.visual.uv is not None and len(mesh.visual.uv) == len(mesh.vertices)
    mat = mesh.visual.material
    assert isinstance(mat, trimesh.visual.material.PBRMaterial)
    assert mat.baseColorTexture is not None and mat.metallicRoughnessTexture is not None
    assert mat.normalTexture is not None and mat.baseColorTexture.size == (64, 64)
    # the file is +Y up: turned back, it is the run's mesh (same box)
    world = np.asarray(mesh.vertices) @ GLTF_FROM_WORLD  # R orthonormal: R^T · p_gltf
    ref = trimesh.load(run / "mesh.ply", process=False)
    np.testing.assert_allclose(world.min(0), ref.vertices.min(0), atol=0.05)
    np.testing.assert_allclose(world.max(0), ref.vertices.max(0), atol=0.05)


def test_khronos_validator_reports_no_issues(run: Path) -> None:
    if not (VALIDATOR / "node_modules" / "gltf-validator").is_dir():
        pytest.fail(
            f"Khronos glTF-Validator missing: run bash scripts/gltf_validator.sh ({VALIDATOR})"
        )
    out = subprocess.run(
        ["node", str(VALIDATOR / "validate.mjs"), str(run / "asset.glb")],
        capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    report = json.loads(out.stdout)
    assert report["numErrors"] == 0 and report["numWarnings"] == 0, report["messages"][:5]


def test_asset_run_into_another_folder(run: Path, tmp_path: Path) -> None:
    events: list[dict] = []
    info = asset_run(run, tmp_path / "a", on_event=events.append, occlusion=False, **SMALL)
    assert {p.name for p in (tmp_path / "a").iterdir()} >= {"asset.glb", "asset_env.hdr"}
    assert info["textures"]["occlusion"].startswith("off")
    steps = [e["step"] for e in events if e.get("name") == "asset"]
    assert steps[0] == "simplify" and steps[-1] == "write"
    assert all(e["overall_done"] <= e["overall_total"] for e in events)


def test_diffuse_model_has_no_environment(run: Path, tmp_path: Path) -> None:
    model, scene = open_run(run)
    model.envmap = None  # what a diffuse plan leaves
    mesh = trimesh.load(run / "mesh.ply", process=False)
    info = export_asset(model, scene.train, tmp_path, mesh, options=AssetOptions(**SMALL))
    assert not info["environment"]["present"] and "diffuse" in info["environment"]["reason"]
    assert not (tmp_path / "asset_env.hdr").exists() and (tmp_path / "asset.glb").is_file()
    assert info["material"]["mean_metallic"] == 0.0


@pytest.mark.parametrize(
    ("options", "field"),
    [({"texture_size": 100}, "texture_size"), ({"faces": 10}, "faces"),
     ({"views": 0}, "views"), ({"colour": 1}, "colour")],
)  # fmt: skip
def test_bad_options_are_named(run: Path, tmp_path: Path, options: dict, field: str) -> None:
    with pytest.raises(AssetError, match=field):
        asset_run(run, tmp_path, **options)
    assert not any(tmp_path.iterdir())  # nothing written


def test_empty_mesh_and_missing_run(run: Path, tmp_path: Path) -> None:
    model, scene = open_run(run)
    with pytest.raises(AssetError, match="no faces"):
        export_asset(model, scene.train, tmp_path, trimesh.Trimesh(), options=AssetOptions(**SMALL))
    with pytest.raises(GlintError, match="checkpoint"):
        asset_run(tmp_path / "nothing", tmp_path / "out")


def test_cancel_stops_without_a_glb(run: Path, tmp_path: Path) -> None:
    model, scene = open_run(run)
    mesh = trimesh.load(run / "mesh.ply", process=False)
    with pytest.raises(AssetCancelledError):
        export_asset(model, scene.train, tmp_path, mesh, options=AssetOptions(**SMALL),
                     should_stop=lambda: True)  # fmt: skip
    assert not (tmp_path / "asset.glb").exists()


def test_cli_export(run: Path, tmp_path: Path) -> None:
    from core.cli import main

    code = main(["export", str(run), "--asset", str(tmp_path), "--faces", "1500",
                 "--texture-size", "64", "--views", "2", "--quiet"])  # fmt: skip
    assert code == 0 and (tmp_path / "asset.glb").is_file()
    assert main(["export", str(run), "--asset", str(tmp_path), "--faces", "20"]) == 2


def test_normal_map_round_trips_through_the_file(tmp_path: Path) -> None:
    """Normals encoded in the texels' tangent frames, written to the .glb and decoded the
    way a glTF viewer does (the file's tangents and handedness, turned back to the
    world) come back: the writer's frames and the file's agree."""
    from core.asset.export import _tangent_space
    from core.asset.glb import GlbMesh, GlbTextures, write_glb
    from core.asset.reference_render import _bilinear, read_glb

    mesh = trimesh.creation.icosphere(subdivisions=3)
    uvm = unwrap(mesh, 256)
    tex = rasterize_atlas(uvm, 256)
    # a smooth tilt of the surface normal (what a bumpier model surface would give)
    tilt = np.stack(
        [np.sin(3 * tex.points[:, 2]), np.cos(2 * tex.points[:, 0]), np.zeros(tex.count)], 1
    )
    want = tex.normals + 0.4 * tilt
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    ts = _tangent_space(tex, want)
    known = tex.mask()
    img = fill_unknown(tex.to_image(ts * 0.5 + 0.5), known, 8)
    png = __import__("core.asset.export", fromlist=["_png"])._png
    flat = np.ones((4, 4, 3)) * 0.5
    write_glb(
        tmp_path / "n.glb",
        GlbMesh(uvm.positions, uvm.normals, uvm.tangents, uvm.uvs, uvm.faces),
        GlbTextures(png(flat, True), png(flat, False), png(img, False)),
    )
    asset = read_glb(tmp_path / "n.glb")
    rot = GLTF_FROM_WORLD
    f = asset.faces[tex.face]
    pos = tex.points @ rot.T  # the texel's point in the file's frame
    tri = asset.positions[f]
    bary = trimesh.triangles.points_to_barycentric(tri, pos)
    interp = lambda a: np.einsum("nk,nkc->nc", bary, a[f])  # noqa: E731
    n = interp(asset.normals)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = interp(asset.tangents[:, :3])
    t = t - n * np.sum(t * n, 1, keepdims=True)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(n, t) * np.where(asset.tangents[f[:, 0], 3] < 0, -1.0, 1.0)[:, None]
    enc = _bilinear(asset.normal_map, interp(asset.uvs)) * 2 - 1
    got = (enc[:, :1] * t + enc[:, 1:2] * b + enc[:, 2:3] * n) @ rot
    got /= np.linalg.norm(got, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(got * want, 1), -1, 1)))
    assert np.median(angle) < 1.5 and np.mean(angle < 5) > 0.95  # 8-bit, bilinear at seams
    # a viewer reading green the other way (DirectX convention) would be far off
    b_wrong = -b
    bad = (enc[:, :1] * t + enc[:, 1:2] * b_wrong + enc[:, 2:3] * n) @ rot
    bad /= np.linalg.norm(bad, axis=1, keepdims=True)
    assert np.median(np.degrees(np.arccos(np.clip(np.sum(bad * want, 1), -1, 1)))) > 5


@pytest.mark.parametrize(("metal", "expect"), [(1.0, "c*L"), (0.0, "c*L+0.04*L")])
def test_reference_render_of_a_constant_sphere(tmp_path: Path, metal: float, expect: str) -> None:
    """Under a uniform map of radiance L, a sphere of constant c and metallic 1 shows
    c·L (F0 = c), one with metallic 0 shows c·L (diffuse, Irr = L) + 0.04·L."""
    from core.asset.export import _png
    from core.asset.glb import GlbMesh, GlbTextures, write_glb
    from core.asset.reference_render import read_glb, render_asset
    from core.scene.synthetic import fibonacci_cameras

    mesh = trimesh.creation.icosphere(subdivisions=3)
    uvm = unwrap(mesh, 64)
    c = np.array([0.6, 0.4, 0.2])
    base = np.ones((8, 8, 3)) * c
    orm = np.ones((8, 8, 3)) * np.array([1.0, 0.0, metal])
    flat = np.ones((8, 8, 3)) * np.array([0.5, 0.5, 1.0])
    write_glb(
        tmp_path / "s.glb",
        GlbMesh(uvm.positions, uvm.normals, uvm.tangents, uvm.uvs, uvm.faces),
        GlbTextures(_png(base, True), _png(orm, False), _png(flat, False), has_occlusion=True),
    )
    L = torch.tensor([1.0, 2.0, 0.5])
    cam = fibonacci_cameras(3, distance=4.0, size=32)[1]
    img, hit = render_asset(read_glb(tmp_path / "s.glb"), L.expand(6, 4, 4, 3), cam, np.ones(3))
    c8 = np.asarray(srgb_to_linear(np.round(np.asarray(linear_to_srgb(c)) * 255) / 255))
    want = c8 * L.numpy() + (0.0 if metal else 0.04 * L.numpy())
    assert hit.mean() > 0.05
    np.testing.assert_allclose(img[hit], np.broadcast_to(want, img[hit].shape), rtol=2e-2)
    assert np.all(img[~hit] == 1.0)


def test_fit_matches_the_reflectance_averaged_over_the_views() -> None:
    """A grey metal seen at angles whose mean Schlick term is κ reflects on average
    F0 (1 − κ) + κ; the fit gives back F0 from that average, not the average itself."""
    f0 = np.array([0.3, 0.6, 0.9])
    kappa = np.array([0.0, 0.1, 0.3])
    w = f0 * (1 - kappa) + kappa
    c, m, e = fit_metallic_roughness(np.zeros((3, 3)), w, kappa)
    np.testing.assert_allclose(m, 1.0, atol=1e-6)
    np.testing.assert_allclose(c[:, 0], f0, atol=1e-6)
    assert e.max() < 1e-10
