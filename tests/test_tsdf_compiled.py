"""The compiled TSDF update (core.meshing.tsdf_compiled) against the torch reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from core.meshing.tsdf import (
    DepthFrame,
    TSDFVolume,
    extract_mesh,
    fuse_depth_frames,
    mask_hull_distance,
)
from core.scene.synthetic import fibonacci_cameras, render_synthetic_view

SIZE = 32


@pytest.fixture(scope="module")
def frames() -> list[DepthFrame]:
    """The sphere from 10 views with everything a frame can carry: carving, colours,
    per-pixel weights, mask-hull distances, depth noise, and a step in the depth
    (nearest-pixel fallback)."""
    g = torch.Generator().manual_seed(0)
    out = []
    for i, cam in enumerate(fibonacci_cameras(10, distance=3.0, size=SIZE)):
        r = render_synthetic_view(cam, shape="sphere", kind="diffuse", samples=2)
        valid = (r.depth > 0) & (r.alpha > 0.5)
        depth = r.depth + 0.002 * torch.randn(r.depth.shape, generator=g, dtype=r.depth.dtype)
        if i % 3 == 0:  # a raised patch: its border is a depth edge
            depth[10:16, 10:16] -= 0.2
        weight = torch.rand(r.depth.shape, generator=g).clamp_min(0.05)
        carve = r.alpha < 0.05
        # a mask a little smaller than the sphere (as a mask the model's surface exceeds):
        # its hull distances raise the band's voxels near the rim
        hull = mask_hull_distance(r.alpha < 0.6) if i % 4 == 1 else None
        out.append(DepthFrame(cam, depth, valid, carve if i % 2 else None, r.rgb, weight, hull))
    return out


def _fuse(frames: list[DepthFrame], compiled: bool) -> TSDFVolume:
    ref, _ = fuse_depth_frames(frames, resolution=48)  # its grid, band and truncation
    vol = TSDFVolume(ref.grid, ref.trunc, ref.index)
    for f in frames:
        vol.integrate(f, compiled=compiled, hull=True)
    return vol


def test_compiled_integration_matches_the_torch_reference(frames) -> None:
    ref, fast = _fuse(frames, False), _fuse(frames, True)
    assert int((ref.weight > 0).sum()) > 1000  # the band was observed
    assert int((ref.hull > 0).sum()) > 100  # the hull bounded some voxels
    for name in ("tsdf", "weight", "color", "color_weight", "hull"):
        a, b = getattr(ref, name), getattr(fast, name)
        # float32 both ways; a voxel whose projection falls within rounding of a pixel
        # border may read the neighbouring pixel, so allow a few such voxels
        close = torch.isclose(a, b, rtol=1e-5, atol=1e-5)
        if close.dim() > 1:
            close = close.all(-1)
        assert float(close.float().mean()) > 0.999, name
    ma, mb = extract_mesh(ref), extract_mesh(fast)
    assert abs(len(ma.faces) - len(mb.faces)) <= 0.001 * len(ma.faces)
    assert np.abs(np.sort(ma.vertices, 0) - np.sort(mb.vertices, 0)).max() < 1e-3
