"""The compiled SSIM blur (core.evaluation.ssim_compiled) against the torch paths.

Values and gradients of ``ssim`` with the numba blur must equal the grouped-convolution
path and the plain 2D window up to rounding, on images smaller than the window, not
square, with one channel or four, in float32 and float64, for any thread count.
"""

from __future__ import annotations

import pytest
import torch

from core.evaluation.ssim import _gaussian_blur, _gaussian_taps, ssim, ssim_reference
from core.evaluation.ssim_compiled import blur_compiled
from core.kernels.pool import set_kernel_threads


def _pair(h: int, w: int, c: int, dtype: torch.dtype, seed: int):
    g = torch.Generator().manual_seed(seed)
    ref = torch.rand(h, w, c, generator=g, dtype=torch.float64)
    img = (ref + 0.15 * torch.randn(h, w, c, generator=g, dtype=torch.float64)).clamp(0, 1)
    return img.to(dtype), ref.to(dtype)


def _value_and_grad(img, ref, **kw):
    x = img.clone().requires_grad_(True)
    s = ssim(x, ref, **kw)
    s.backward()
    return s.detach(), x.grad


@pytest.mark.parametrize(
    ("h", "w", "c"), [(24, 24, 3), (7, 13, 3), (3, 2, 1), (40, 33, 4), (128, 96, 3)]
)
def test_compiled_ssim_equals_the_torch_paths_in_float64(h: int, w: int, c: int) -> None:
    img, ref = _pair(h, w, c, torch.float64, h * w + c)
    v_c, g_c = _value_and_grad(img, ref, compiled=True)
    v_t, g_t = _value_and_grad(img, ref, compiled=False)
    torch.testing.assert_close(v_c, v_t, rtol=0, atol=1e-12)
    torch.testing.assert_close(v_c, ssim_reference(img, ref), rtol=0, atol=1e-12)
    torch.testing.assert_close(g_c, g_t, rtol=1e-9, atol=1e-14)


def test_compiled_ssim_in_float32_is_the_float64_value_to_rounding() -> None:
    img, ref = _pair(64, 80, 3, torch.float32, 5)
    v_c, g_c = _value_and_grad(img, ref, compiled=True)
    v_64, g_64 = _value_and_grad(img.double(), ref.double(), compiled=False)
    assert v_c.dtype == torch.float32 and g_c.dtype == torch.float32
    assert abs(float(v_c) - float(v_64)) < 2e-6
    torch.testing.assert_close(g_c.double(), g_64, rtol=1e-3, atol=1e-4 * float(g_64.abs().max()))


def test_the_cpu_default_is_the_compiled_blur_and_gradients_reach_both_images() -> None:
    img, ref = _pair(20, 17, 3, torch.float32, 9)
    a, b = img.clone().requires_grad_(True), ref.clone().requires_grad_(True)
    ssim(a, b).backward()
    a2, b2 = img.clone().requires_grad_(True), ref.clone().requires_grad_(True)
    ssim(a2, b2, compiled=False).backward()
    torch.testing.assert_close(a.grad, a2.grad, rtol=1e-4, atol=1e-7)
    torch.testing.assert_close(b.grad, b2.grad, rtol=1e-4, atol=1e-7)


def test_blur_is_its_own_adjoint_and_passes_gradcheck() -> None:
    g = torch.Generator().manual_seed(3)
    maps = torch.rand(2, 9, 12, generator=g, dtype=torch.float64, requires_grad=True)
    taps = _gaussian_taps(5, 1.0, maps)
    assert torch.autograd.gradcheck(lambda m: blur_compiled(m, taps), (maps,))
    got = blur_compiled(maps.detach(), taps)
    want = _gaussian_blur(maps.detach()[None], taps)[0]
    torch.testing.assert_close(got, want, rtol=0, atol=1e-14)


def test_thread_count_does_not_change_the_blur() -> None:
    g = torch.Generator().manual_seed(4)
    maps = torch.rand(9, 50, 41, generator=g)
    taps = _gaussian_taps(11, 1.5, maps)
    try:
        set_kernel_threads(1)
        one = blur_compiled(maps, taps)
        set_kernel_threads(3)
        three = blur_compiled(maps, taps)
    finally:
        set_kernel_threads(None)
    assert torch.equal(one, three)


def test_blur_rejects_what_its_backward_cannot_reuse() -> None:
    maps = torch.rand(2, 8, 8)
    with pytest.raises(ValueError, match="symmetric"):
        blur_compiled(maps, torch.tensor([0.2, 0.5, 0.3]))
    with pytest.raises(ValueError, match="odd"):
        blur_compiled(maps, torch.tensor([0.5, 0.5]))
    with pytest.raises(ValueError, match=r"\(K, H, W\)"):
        blur_compiled(maps[0], torch.tensor([0.25, 0.5, 0.25]))


def test_fused_ssim_without_gradients_gives_the_same_value() -> None:
    """Evaluations (no gradient) skip the partial maps and read the same SSIM; constant
    images (zero variance, where S's numerator and denominator both shrink) are finite."""
    img, ref = _pair(30, 21, 3, torch.float32, 13)
    with torch.no_grad():
        plain = ssim(img, ref, compiled=False)
        fused = ssim(img, ref)
    torch.testing.assert_close(fused, plain, rtol=0, atol=2e-6)
    flat = torch.full((12, 12, 3), 0.4)
    v, g = _value_and_grad(flat, torch.full((12, 12, 3), 0.6), compiled=True)
    v_t, g_t = _value_and_grad(flat, torch.full((12, 12, 3), 0.6), compiled=False)
    assert torch.isfinite(g).all()
    torch.testing.assert_close(v, v_t, rtol=0, atol=1e-5)  # E[x²] − μ² cancels in float32
    torch.testing.assert_close(g, g_t, rtol=1e-4, atol=1e-7)


def test_fused_ssim_rejects_what_it_cannot_differentiate() -> None:
    from core.evaluation.ssim_compiled import ssim_compiled

    img, ref = _pair(8, 8, 3, torch.float32, 1)
    taps = _gaussian_taps(11, 1.5, img)
    with pytest.raises(ValueError, match="same"):
        ssim_compiled(img, ref[:, :4], taps, 1e-4, 9e-4)
    with pytest.raises(ValueError, match="ref requires grad"):
        ssim_compiled(img, ref.clone().requires_grad_(True), taps, 1e-4, 9e-4)
    with pytest.raises(ValueError, match="float64"):
        ssim_compiled(img, ref.double(), taps, 1e-4, 9e-4)
