"""bench.envmap_ceiling: the true map stored as a cube, sharp and at a roughness's level."""

from pathlib import Path

import torch

from bench.envmap_ceiling import blurred_cube, true_cube
from core.evaluation.envmap_accuracy import TrueEnvmap
from core.render.envmap_io import LatLong


def _truth(image: torch.Tensor) -> TrueEnvmap:
    return TrueEnvmap(image, LatLong(), None, Path("envmap.exr"))


def test_a_constant_map_stays_constant_sharp_and_blurred() -> None:
    cube = true_cube(_truth(torch.full((32, 64, 3), 0.7)), 8)
    assert cube.shape == (6, 8, 8, 3)
    torch.testing.assert_close(cube, torch.full_like(cube, 0.7))
    torch.testing.assert_close(blurred_cube(cube, 0.6), cube, atol=1e-5, rtol=0)


def test_the_cube_holds_the_true_maps_brightness_where_it_points() -> None:
    img = torch.zeros(64, 128, 3)
    img[:32] = 1.0  # upper hemisphere (+Z) bright, lower dark
    cube = true_cube(_truth(img), 8)
    assert float(cube[4].min()) > 0.99  # the +Z face
    assert float(cube[5].max()) < 0.01  # the -Z face


def test_roughness_blurs_a_bright_texel_into_its_neighbours_and_keeps_its_energy() -> None:
    cube = torch.zeros(6, 16, 16, 1)
    cube[0, 7:9, 7:9] = 1.0
    mirror = blurred_cube(cube, 0.0)
    torch.testing.assert_close(mirror, cube, atol=1e-5, rtol=0)  # ρ = 0 reads level 0
    rough = blurred_cube(cube, 0.5)
    assert float(rough[0, 7, 7]) < 0.5  # the peak spreads out
    assert float(rough[0, 4, 4]) > 0.01  # into texels it never lit
    assert abs(float(rough.sum()) - float(cube.sum())) < 0.5 * float(cube.sum())
