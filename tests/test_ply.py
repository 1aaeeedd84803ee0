"""3DGS PLY export/import: layout, interoperability, bit-exact round trip, clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from plyfile import PlyData, PlyElement

from core.errors import SceneError
from core.outputs.ply import DEFAULT_IMPORT_REFL, load_ply, save_ply
from core.render.gaussians import PARAM_SHAPES, Gaussians
from core.render.roughness import ROUGH_KEY, add_roughness_state, has_roughness, roughness

# The 3DGS layout written out by hand (not via core.outputs.ply) so a change there is caught.
EXPECTED_NAMES = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    + ["refl_logit"]
)


def random_gaussians(n: int = 37, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    params = {k: torch.randn(n, *s, generator=g) * 3 for k, s in PARAM_SHAPES.items()}
    return Gaussians(params)


def write_3dgs_style(path: Path, g: Gaussians, n_rest: int, with_refl: bool = False) -> None:
    """What 3DGS's ``GaussianModel.save_ply`` writes (degree from ``n_rest`` per channel)."""
    p = {k: v.detach().numpy() for k, v in g.params.items()}
    n = g.num
    f_dc = p["sh_dc"].transpose(0, 2, 1).reshape(n, -1)
    f_rest = p["sh_rest"][:, :n_rest].transpose(0, 2, 1).reshape(n, -1)
    attrs = [
        p["means"],
        np.zeros((n, 3), np.float32),
        f_dc,
        f_rest,
        p["opacity_logits"][:, None],
        p["log_scales"],
        p["quats"],
    ]
    names = ["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
    names += [f"f_rest_{i}" for i in range(f_rest.shape[1])]
    names += ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    if with_refl:
        attrs.append(p["refl_logits"][:, None])
        names.append("refl_logit")
    data = np.concatenate(attrs, axis=1)
    arr = np.empty(n, dtype=[(nm, "f4") for nm in names])
    arr[:] = list(map(tuple, data))
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))


def test_layout_names_order_and_binary(tmp_path: Path) -> None:
    g = random_gaussians()
    path = save_ply(g, tmp_path / "g.ply")
    ply = PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["vertex"]
    v = ply["vertex"]
    assert [p.name for p in v.properties] == EXPECTED_NAMES
    assert all(v.data.dtype[nm] == np.dtype("<f4") for nm in EXPECTED_NAMES)
    assert not ply.text and ply.byte_order == "<"
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert len(v.data) == g.num
    # Raw values: the unconstrained parameters, unchanged.
    np.testing.assert_array_equal(v["opacity"], g.params["opacity_logits"].detach().numpy())
    np.testing.assert_array_equal(v["scale_1"], g.params["log_scales"][:, 1].detach().numpy())
    np.testing.assert_array_equal(v["rot_0"], g.params["quats"][:, 0].detach().numpy())
    np.testing.assert_array_equal(v["refl_logit"], g.params["refl_logits"].detach().numpy())
    # nx ny nz: the Eq. 6 normal.
    normals = np.stack([v["nx"], v["ny"], v["nz"]], axis=1)
    np.testing.assert_allclose(normals, g.normals().detach().numpy(), atol=1e-7)
    assert not list(tmp_path.glob("*.tmp"))


def test_f_rest_is_channel_major(tmp_path: Path) -> None:
    g = random_gaussians(4)
    # sh_rest[i, k, c] = 1000·i + 100·c + k: every coefficient distinguishable.
    i, k, c = torch.meshgrid(torch.arange(4), torch.arange(15), torch.arange(3), indexing="ij")
    with torch.no_grad():
        g.params["sh_rest"].copy_((1000 * i + 100 * c + k).float())
        g.params["sh_dc"].copy_(torch.tensor([7.0, 8.0, 9.0]).expand(4, 1, 3))
    v = PlyData.read(str(save_ply(g, tmp_path / "g.ply")))["vertex"]
    for idx in range(4):
        for ch in range(3):
            for coef in range(15):
                assert v[f"f_rest_{ch * 15 + coef}"][idx] == 1000 * idx + 100 * ch + coef
    np.testing.assert_array_equal(v["f_dc_0"], 7.0)
    np.testing.assert_array_equal(v["f_dc_2"], 9.0)


def test_trimesh_opens_export(tmp_path: Path) -> None:
    g = random_gaussians(53)
    loaded = trimesh.load(str(save_ply(g, tmp_path / "g.ply")))
    assert isinstance(loaded, (trimesh.PointCloud, trimesh.Trimesh))
    assert len(loaded.vertices) == 53
    np.testing.assert_allclose(loaded.vertices, g.means.detach().numpy(), rtol=0, atol=1e-6)


def test_round_trip_is_bit_exact(tmp_path: Path) -> None:
    g = random_gaussians(101, seed=3)
    with torch.no_grad():  # awkward values: denormals, extremes, negative zero
        g.params["means"][0] = torch.tensor([1e-40, -0.0, 3.4e38])
        g.params["quats"][1] = 0.0
    h = load_ply(save_ply(g, tmp_path / "g.ply"))
    assert set(h.params.keys()) == set(g.params.keys())
    for k in g.params:
        assert h.params[k].dtype == torch.float32
        assert torch.equal(h.params[k], g.params[k].detach()), k
        # Bitwise, including the sign of zero.
        assert torch.equal(h.params[k].view(torch.int32), g.params[k].detach().view(torch.int32))
    assert h.sh_degree == 3
    # And once more through our own output.
    h2 = load_ply(save_ply(h, tmp_path / "h.ply"))
    assert all(torch.equal(h2.params[k], h.params[k]) for k in h.params)


def test_imports_3dgs_files_of_each_degree(tmp_path: Path) -> None:
    g = random_gaussians(9, seed=4)
    for degree, n_rest in ((0, 0), (1, 3), (2, 8), (3, 15)):
        path = tmp_path / f"deg{degree}.ply"
        write_3dgs_style(path, g, n_rest)
        h = load_ply(path)
        assert h.sh_degree == degree
        assert torch.equal(h.params["sh_dc"], g.params["sh_dc"].detach())
        assert torch.equal(
            h.params["sh_rest"][:, :n_rest], g.params["sh_rest"][:, :n_rest].detach()
        )
        assert torch.all(h.params["sh_rest"][:, n_rest:] == 0)
        for k in ("means", "log_scales", "quats", "opacity_logits"):
            assert torch.equal(h.params[k], g.params[k].detach()), k
        torch.testing.assert_close(h.w_r, torch.full((9,), DEFAULT_IMPORT_REFL))
        assert torch.isfinite(h.params["refl_logits"]).all()
    path = tmp_path / "refl.ply"
    write_3dgs_style(path, g, 15, with_refl=True)
    assert torch.equal(load_ply(path).params["refl_logits"], g.params["refl_logits"].detach())


def _rewrite_without(src: Path, dst: Path, drop: str) -> None:
    v = PlyData.read(str(src))["vertex"].data
    keep = [nm for nm in v.dtype.names if nm != drop]
    arr = np.empty(len(v), dtype=[(nm, "f4") for nm in keep])
    for nm in keep:
        arr[nm] = v[nm]
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(dst))


@pytest.mark.parametrize("missing", ["x", "opacity", "scale_2", "rot_3", "f_dc_1"])
def test_missing_property_is_a_clear_error(tmp_path: Path, missing: str) -> None:
    src = save_ply(random_gaussians(5), tmp_path / "g.ply")
    dst = tmp_path / "broken.ply"
    _rewrite_without(src, dst, missing)
    with pytest.raises(SceneError) as err:
        load_ply(dst)
    assert err.value.field == missing
    assert err.value.file == str(dst)
    assert missing in str(err.value) and "broken.ply" in str(err.value)


def test_bad_f_rest_count_and_gap(tmp_path: Path) -> None:
    src = save_ply(random_gaussians(5), tmp_path / "g.ply")
    gap = tmp_path / "gap.ply"
    _rewrite_without(src, gap, "f_rest_7")
    with pytest.raises(SceneError) as err:
        load_ply(gap)
    assert err.value.field == "f_rest_7"
    # 6 coefficients (2 per channel) is no SH degree.
    v = PlyData.read(str(src))["vertex"].data
    names = [nm for nm in v.dtype.names if not nm.startswith("f_rest_")]
    names[9:9] = [f"f_rest_{i}" for i in range(6)]
    arr = np.zeros(len(v), dtype=[(nm, "f4") for nm in names])
    for nm in names:
        arr[nm] = v[nm]
    odd = tmp_path / "odd.ply"
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(odd))
    with pytest.raises(SceneError) as err:
        load_ply(odd)
    assert err.value.field == "f_rest"


def test_non_finite_and_garbage_files(tmp_path: Path) -> None:
    g = random_gaussians(5)
    with torch.no_grad():
        g.params["log_scales"][2, 1] = float("nan")
    with pytest.raises(ValueError, match="log_scales"):
        save_ply(g, tmp_path / "refused.ply")
    assert not list(tmp_path.iterdir())
    path = tmp_path / "nan.ply"
    write_3dgs_style(path, g, 15)
    with pytest.raises(SceneError) as err:
        load_ply(path)
    assert err.value.field == "scale_1"
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"this is not a ply file\n")
    with pytest.raises(SceneError) as err:
        load_ply(junk)
    assert err.value.file == str(junk)
    with pytest.raises(SceneError, match="not found"):
        load_ply(tmp_path / "absent.ply")


def test_ascii_ply_loads(tmp_path: Path) -> None:
    g = random_gaussians(3)
    path = save_ply(g, tmp_path / "g.ply")
    ply = PlyData.read(str(path))
    ascii_path = tmp_path / "ascii.ply"
    PlyData(ply.elements, text=True).write(str(ascii_path))
    h = load_ply(ascii_path)
    for k in g.params:
        torch.testing.assert_close(h.params[k], g.params[k].detach(), rtol=1e-6, atol=1e-6)


def rough_gaussians(n: int = 23, seed: int = 5) -> Gaussians:
    g = random_gaussians(n, seed)
    add_roughness_state(g)
    with torch.no_grad():  # distinct per splat, extremes included
        g.params[ROUGH_KEY].copy_(torch.randn(n, generator=torch.Generator().manual_seed(seed)) * 3)
        g.params[ROUGH_KEY][0] = -30.0
    return g


def test_roughness_is_exported_after_refl_logit_and_read_back(tmp_path: Path) -> None:
    g = rough_gaussians()
    v = PlyData.read(str(save_ply(g, tmp_path / "g.ply")))["vertex"]
    assert [p.name for p in v.properties] == [*EXPECTED_NAMES, "rough_logit"]
    assert v.data.dtype["rough_logit"] == np.dtype("<f4")
    # the logit, as refl_logit: ρ = sigmoid(rough_logit)
    np.testing.assert_array_equal(v["rough_logit"], g.params[ROUGH_KEY].detach().numpy())
    h = load_ply(tmp_path / "g.ply")
    assert has_roughness(h) and set(h.params) == set(g.params)
    for k in g.params:
        assert torch.equal(h.params[k].view(torch.int32), g.params[k].detach().view(torch.int32)), k
    torch.testing.assert_close(roughness(h), roughness(g).detach())
    assert h.params[ROUGH_KEY].requires_grad  # a parameter like the others


def test_files_without_roughness_load_without_it(tmp_path: Path) -> None:
    # ours from before roughness (and any model without it): no property, no state
    plain = random_gaussians(6)
    v = PlyData.read(str(save_ply(plain, tmp_path / "plain.ply")))["vertex"]
    assert "rough_logit" not in [p.name for p in v.properties]
    assert not has_roughness(load_ply(tmp_path / "plain.ply"))
    # a rough model's file with the property taken out reads as a mirror model
    src = save_ply(rough_gaussians(6), tmp_path / "rough.ply")
    _rewrite_without(src, tmp_path / "old.ply", "rough_logit")
    old = load_ply(tmp_path / "old.ply")
    assert not has_roughness(old) and old.num == 6
    # 3DGS files too
    write_3dgs_style(tmp_path / "3dgs.ply", plain, 15)
    assert not has_roughness(load_ply(tmp_path / "3dgs.ply"))


def test_non_finite_roughness_is_refused_both_ways(tmp_path: Path) -> None:
    g = rough_gaussians(4)
    with torch.no_grad():
        g.params[ROUGH_KEY][2] = float("inf")
    with pytest.raises(ValueError, match=ROUGH_KEY):
        save_ply(g, tmp_path / "refused.ply")
    good = save_ply(rough_gaussians(4), tmp_path / "g.ply")
    v = PlyData.read(str(good))["vertex"].data.copy()
    v["rough_logit"][1] = np.nan
    bad = tmp_path / "nan.ply"
    PlyData([PlyElement.describe(v, "vertex")]).write(str(bad))
    with pytest.raises(SceneError) as err:
        load_ply(bad)
    assert err.value.field == "rough_logit"
