"""Env map files: cube cross (lossless), lat-long convention and round trips, previews."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from core.errors import SceneError
from core.render.envmap import EnvMap, texel_directions
from core.render.envmap_io import (
    CROSS_BLOCKS,
    LatLong,
    cross_to_cube,
    cube_to_cross,
    cube_to_equirect,
    equirect_to_cube,
    init_envmap_from_file,
    load_envmap_texels,
    sample_equirect,
    save_cube_cross,
    save_envmap,
)
from core.scene.imageio import linear_to_srgb, read_image, read_image_array, write_image

F64 = torch.float64
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DEV_MAPS = sorted(DATA.glob("*/envmap.exr")) if DATA.is_dir() else []


def smooth_env(d: torch.Tensor) -> torch.Tensor:
    d = d / d.norm(dim=-1, keepdim=True)
    x, y, z = d.unbind(-1)
    return torch.stack([1 + 0.5 * x, 1 + 0.5 * y + 0.25 * z * z, 1 + 0.5 * torch.sin(2 * z)], -1)


def psnr_tonemapped(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR of HDR images after Reinhard x / (1 + x), so bright lights don't dominate."""
    mse = (a / (1 + a) - b / (1 + b)).square().mean()
    return float(-10 * torch.log10(mse))


# -- cube cross ---------------------------------------------------------------


def test_cross_layout_folds_into_the_cube():
    """Pixels that touch across a block boundary in the cross are texel neighbours on
    the cube, and the +Z face sits in the middle of the row of four."""
    r = 8
    cross = cube_to_cross(texel_directions(r, F64))
    assert cross.shape == (3 * r, 4 * r, 3)
    assert CROSS_BLOCKS[4] == (1, 1)
    used = torch.zeros(3, 4, dtype=torch.bool)
    for br, bc in CROSS_BLOCKS:
        used[br, bc] = True
    texel_angle = 2 * math.atan(1 / r)
    checked = 0
    for br in range(3):
        for bc in range(4):
            for dr, dc in ((0, 1), (1, 0)):
                nr, nc = br + dr, bc + dc
                if nr > 2 or nc > 3 or not (used[br, bc] and used[nr, nc]):
                    continue
                if dc:  # last column of this block vs first column of the next
                    a = cross[br * r : (br + 1) * r, (bc + 1) * r - 1]
                    b = cross[br * r : (br + 1) * r, (bc + 1) * r]
                else:
                    a = cross[(br + 1) * r - 1, bc * r : (bc + 1) * r]
                    b = cross[(br + 1) * r, bc * r : (bc + 1) * r]
                ang = torch.acos((a * b).sum(-1).clamp(-1, 1))
                assert (ang < 1.01 * texel_angle).all(), (br, bc, dr, dc)
                checked += 1
    assert checked == 5  # 3 joins in the middle row, +Y and -Y onto +Z
    assert torch.equal(cross_to_cube(cross), texel_directions(r, F64))
    assert cross[:r, :r].abs().sum() == 0  # unused blocks are black


def test_cube_cross_save_and_load_is_exact(tmp_path):
    g = torch.Generator().manual_seed(0)
    hdr = torch.exp(torch.randn(6, 16, 16, 3, generator=g) * 3)  # 1e-4 .. 1e4
    path = save_cube_cross(tmp_path / "env_cross.exr", hdr)
    arr, is_float = read_image_array(path)
    assert is_float and arr.shape == (48, 64, 3)
    assert torch.equal(load_envmap_texels(path), hdr)  # bit-exact through the file
    env = EnvMap(resolution=16)
    init_envmap_from_file(env, path)
    torch.testing.assert_close(env.texels(), hdr.clamp_min(env.min_value), rtol=2e-6, atol=0)
    # the learned map itself: save -> load -> identical radiance
    again = EnvMap(resolution=16)
    init_envmap_from_file(again, save_cube_cross(tmp_path / "again.exr", env))
    torch.testing.assert_close(again.texels(), env.texels(), rtol=2e-6, atol=0)


def test_cross_loaded_at_another_resolution_is_resampled_seamlessly(tmp_path):
    path = save_cube_cross(tmp_path / "c.exr", smooth_env(texel_directions(16, torch.float32)))
    cube = load_envmap_texels(path, resolution=24)
    assert cube.shape == (6, 24, 24, 3)
    want = smooth_env(texel_directions(24, torch.float32))
    assert (cube - want).abs().max() < 0.25 / 16


# -- lat-long convention --------------------------------------------------------


def test_latlong_default_is_the_dev_data_convention():
    h, w = 64, 128
    ll = LatLong()
    dirs = torch.tensor(
        [[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0], [0, 0, -1.0]], dtype=F64
    )
    row, col = ll.to_pixel(dirs, h, w)
    # middle column faces +X, the column at W/4 faces +Y, the top row is +Z
    torch.testing.assert_close(
        col[:4], torch.tensor([w / 2, w / 4, 0.0, 3 * w / 4], dtype=F64) - 0.5
    )
    torch.testing.assert_close(row, torch.tensor([(h - 1) / 2] * 4 + [0.0, h - 1.0], dtype=F64))
    # the explicit formula of the data README at a generic direction
    d = torch.tensor([[0.3, -0.7, 0.4]], dtype=F64)
    d = d / d.norm()
    u = (0.5 - math.atan2(-0.7, 0.3) / (2 * math.pi)) % 1.0
    theta = math.acos(d[0, 2].item())
    row, col = ll.to_pixel(d, h, w)
    assert col.item() == pytest.approx(u * w - 0.5)
    assert row.item() == pytest.approx(theta / math.pi * (h - 1))
    # a marker image: sampling at the axes picks the marked pixels
    img = torch.zeros(h, w, 1, dtype=F64)
    img[h // 2 - 1 : h // 2 + 1, w // 2 - 1 : w // 2 + 1] = 7.0  # around +X
    img[0] = 3.0  # the +Z pole row
    assert sample_equirect(img, dirs[0:1]).item() == pytest.approx(7.0)
    assert sample_equirect(img, dirs[4:5]).item() == pytest.approx(3.0)
    assert sample_equirect(img, dirs[2:3]).item() == 0.0


@pytest.mark.parametrize("rows", ["endpoints", "centers"])
@pytest.mark.parametrize("rotation", [None, ((1, 0, 0), (0, 0, -1), (0, 1, 0))])
def test_latlong_pixel_directions_invert_to_pixel(rows, rotation):
    h, w = 16, 32
    ll = LatLong(rotation=rotation, rows=rows)
    d = ll.pixel_directions(h, w, F64)
    row, col = ll.to_pixel(d, h, w)
    jj, ii = torch.meshgrid(torch.arange(h, dtype=F64), torch.arange(w, dtype=F64), indexing="ij")
    torch.testing.assert_close(row, jj, atol=1e-9, rtol=0)
    off_pole = slice(1, -1) if rows == "endpoints" else slice(None)  # pole rows: any column
    col = torch.remainder(col + 0.5, w) - 0.5
    torch.testing.assert_close(col[off_pole], ii[off_pole], atol=1e-9, rtol=0)
    up = torch.tensor([0.0, 0.0, 1.0] if rotation is None else [0.0, 1.0, 0.0], dtype=F64)
    assert ((d[0] @ up) > math.cos(math.pi / h)).all()  # the top row looks up


def test_equirect_columns_wrap_without_a_seam():
    h, w = 32, 64
    img = smooth_env(LatLong().pixel_directions(h, w, F64))
    phi = torch.linspace(math.pi - 0.2, math.pi + 0.2, 801, dtype=F64)  # across -X (the wrap)
    d = torch.stack([phi.cos() * 0.8, phi.sin() * 0.8, torch.full_like(phi, 0.6)], -1)
    vals = sample_equirect(img, d)
    assert (vals[1:] - vals[:-1]).abs().max() < 4 * 0.4 / 800
    assert (vals - smooth_env(d)).abs().max() < 0.01


# -- round trips ------------------------------------------------------------------


def test_generated_map_equirect_cube_equirect_round_trip():
    h, w = 64, 128
    eq = smooth_env(LatLong().pixel_directions(h, w, F64))
    cube = equirect_to_cube(eq, 64)
    torch.testing.assert_close(cube, smooth_env(texel_directions(64, F64)), atol=2e-3, rtol=0)
    back = cube_to_equirect(cube, h, w)
    assert (back - eq).abs().max() < 3e-3  # measured 1e-3: two bilinear resamplings
    # supersampling is a box filter: still close, and smoother never means shifted
    cube_ss = equirect_to_cube(eq, 32, supersample=3)
    assert (cube_ss - smooth_env(texel_directions(32, F64))).abs().max() < 5e-3


@pytest.mark.shared_data
@pytest.mark.skipif(not DEV_MAPS, reason="dev data not present")
@pytest.mark.parametrize("path", DEV_MAPS, ids=lambda p: p.parent.name)
def test_dev_envmap_round_trip(path):
    """Real HDR maps (1024×512, lights up to ~1e3), area-downsampled 8× to 64×128, to a
    128² cube (about 2 texels per lat-long pixel) and back, rows within 1/8 of the poles
    left out. Two bilinear resamplings blur point lights into their neighbours, so the
    bound is on tone-mapped PSNR (measured 28-35 dB) and on the median relative error
    (measured 0.1-2 %); a rotated or mirrored convention scores far below both."""
    img, _ = read_image(path)
    small = torch.nn.functional.avg_pool2d(img.permute(2, 0, 1)[None], 8)[0].permute(1, 2, 0)
    h, w = small.shape[:2]
    back = cube_to_equirect(equirect_to_cube(small, 128), h, w)
    rows = slice(h // 8, h - h // 8)
    a, b = back[rows], small[rows]
    assert psnr_tonemapped(a, b) > 26.0
    rel = ((a - b).abs() / (b.abs() + 0.05)).median()
    assert rel < 0.06
    flipped = cube_to_equirect(equirect_to_cube(small.flip(1), 128), h, w)[rows]
    assert psnr_tonemapped(flipped, b) < 22.0  # the comparison can tell a wrong convention


# -- writing ----------------------------------------------------------------------


def test_save_envmap_writes_cross_latlong_and_preview(tmp_path):
    env = EnvMap(resolution=16)
    g = torch.Generator().manual_seed(4)
    env.set_texels(smooth_env(texel_directions(16)) * torch.rand(1, 1, 1, 3, generator=g) * 1.5)
    paths = save_envmap(env, tmp_path / "out")
    assert set(paths) == {"cross", "equirect", "preview"}
    cross, _ = read_image(paths["cross"])
    assert torch.equal(cross, cube_to_cross(env.texels().detach()))
    eq, _ = read_image(paths["equirect"])
    assert eq.shape == (32, 64, 3)  # 2R × 4R by default
    torch.testing.assert_close(eq, cube_to_equirect(env.texels().detach(), 32))
    assert eq.max() > 1.0  # HDR values survive in the EXR
    png, is_float = read_image_array(paths["preview"])
    assert not is_float and png.shape == (32, 64, 3)
    want = np.clip(linear_to_srgb(eq.numpy()), 0, 1)  # tone mapping = clip
    assert np.abs(png - want).max() <= 0.5 / 255 + 1e-6
    assert load_envmap_texels(paths["equirect"]).shape == (6, 16, 16, 3)


def test_luminance_load_and_bad_files(tmp_path):
    eq = torch.rand(8, 16, 3)
    p = write_image(tmp_path / "eq.exr", eq)
    one = load_envmap_texels(p, resolution=4, channels=1)
    assert one.shape == (6, 4, 4, 1)
    rgb = load_envmap_texels(p, resolution=4)
    torch.testing.assert_close(one[..., 0], rgb @ torch.tensor([0.2126, 0.7152, 0.0722]))
    bad = write_image(tmp_path / "bad.exr", torch.rand(10, 15, 3))
    with pytest.raises(SceneError, match=r"bad\.exr"):
        load_envmap_texels(bad)
    with pytest.raises(SceneError):
        load_envmap_texels(tmp_path / "missing.exr")
    with pytest.raises(ValueError):
        save_cube_cross(tmp_path / "x.exr", torch.rand(6, 4, 4, 2))
    scaled = load_envmap_texels(p, resolution=4, scale=2.0)
    torch.testing.assert_close(scaled, 2.0 * rgb)
