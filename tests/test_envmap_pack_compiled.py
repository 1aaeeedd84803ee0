"""The compiled padded mip chain (core.render.envmap_pack_compiled) against the torch
reference it replaces on the CPU: ``pad_cube`` and ``_packed_levels(cube_mip_chain(·))``."""

from __future__ import annotations

import pytest
import torch

from core.render.envmap import pad_cube, sample_cube
from core.render.envmap_mips import _packed_levels, cube_mip_chain, sample_cube_lod
from core.render.envmap_pack_compiled import PARALLEL_ROWS, packed_cube_levels


def _reference(texels: torch.Tensor, mips: bool) -> tuple[torch.Tensor, list[int], list[int]]:
    if mips:
        return _packed_levels(cube_mip_chain(texels))
    r = texels.shape[1]
    return pad_cube(texels).reshape(-1, texels.shape[-1]), [0], [r + 2]


@pytest.mark.parametrize("mips", [True, False])
@pytest.mark.parametrize("resolution", [1, 2, 6, 16, 32, 64])  # 64: the threaded gather
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_values_layout_and_gradients_match_the_torch_ops(resolution, mips, dtype) -> None:
    gen = torch.Generator().manual_seed(resolution)
    texels = torch.rand(6, resolution, resolution, 3, generator=gen, dtype=dtype)
    texels.requires_grad_(True)
    ref, ref_off, ref_sizes = _reference(texels, mips)
    got, off, sizes = packed_cube_levels(texels, mips)
    assert (off, sizes) == (ref_off, ref_sizes) and got.dtype == dtype
    tol = 1e-6 if dtype == torch.float32 else 1e-13
    torch.testing.assert_close(got, ref, rtol=tol, atol=tol)
    weights = torch.randn(ref.shape, generator=gen, dtype=dtype)
    (g_ref,) = torch.autograd.grad((ref * weights).sum(), texels)
    (g_got,) = torch.autograd.grad((got * weights).sum(), texels)
    torch.testing.assert_close(g_got, g_ref, rtol=tol * 4, atol=tol * 4)


def test_the_largest_case_above_is_split_over_threads() -> None:
    assert 6 * (64 + 2) ** 2 >= PARALLEL_ROWS > 6 * (32 + 2) ** 2


def test_gradcheck_through_a_chain_that_ends_on_an_odd_size() -> None:
    texels = torch.rand(6, 6, 6, 2, dtype=torch.float64, requires_grad=True)  # 6 -> 3
    assert torch.autograd.gradcheck(lambda t: packed_cube_levels(t, True)[0], (texels,))


def test_a_nan_texel_reaches_the_same_rows_as_in_torch() -> None:
    texels = torch.rand(6, 8, 8, 3)
    texels[2, 0, 7, 1] = float("nan")  # an edge texel: border rows of other faces too
    ref, _, _ = _reference(texels, True)
    got, _, _ = packed_cube_levels(texels, True)
    assert torch.equal(got.isnan(), ref.isnan()) and got.isnan().any()


def test_a_map_that_is_not_a_cube_is_refused() -> None:
    with pytest.raises(ValueError, match=r"\(6, R, R, C\)"):
        packed_cube_levels(torch.rand(6, 8, 4, 3), True)


def test_both_lookups_agree_with_their_torch_paths_end_to_end() -> None:
    gen = torch.Generator().manual_seed(3)
    texels = torch.rand(6, 16, 16, 3, generator=gen, requires_grad=True)
    dirs = torch.randn(500, 3, generator=gen)
    lod = torch.rand(500, generator=gen) * 4.0
    for fn in (lambda c: sample_cube_lod(texels, dirs, lod, compiled=c),
               lambda c: sample_cube(texels, dirs, compiled=c)):  # fmt: skip
        out_c, out_t = fn(True), fn(False)
        torch.testing.assert_close(out_c, out_t, rtol=1e-5, atol=1e-6)
        (g_c,) = torch.autograd.grad(out_c.square().sum(), texels)
        (g_t,) = torch.autograd.grad(out_t.square().sum(), texels)
        torch.testing.assert_close(g_c, g_t, rtol=1e-4, atol=1e-5)
