"""The mesher's depth at oblique pixels: Eq. 8 gives way to Eq. 5 along a cos ramp."""

from __future__ import annotations

import math

import pytest
import torch

from core.render.depth_geometry import grazing_blend
from core.scene.synthetic import fibonacci_cameras


def _normal_at(camera, cos: float) -> torch.Tensor:  # type: ignore[no-untyped-def]
    """(H, W, 3) camera-space normals making angle acos(cos) with each pixel's ray."""
    rays = camera.camera_rays(torch.float32, torch.device("cpu"))
    r = rays / rays.norm(dim=-1, keepdim=True)
    side = torch.linalg.cross(r, torch.tensor([0.0, 1.0, 0.0]).expand_as(r))
    side = side / side.norm(dim=-1, keepdim=True)
    return cos * r + math.sqrt(1.0 - cos * cos) * side


@pytest.mark.parametrize(
    ("cos", "weight"),
    [(1.0, 1.0), (0.8, 1.0), (0.6, 0.5), (0.4, 0.0), (0.1, 0.0)],
)
def test_weight_of_the_planar_depth_follows_the_ramp(cos: float, weight: float) -> None:
    cam = fibonacci_cameras(1, distance=3.0, size=8)[0]
    planar = torch.full((8, 8), 2.0)
    centre = torch.full((8, 8), 3.0)
    valid = torch.ones(8, 8, dtype=torch.bool)
    # any length and sign of the blended normal: only the angle counts
    normal = -0.3 * _normal_at(cam, cos)
    out = grazing_blend(planar, valid, centre, normal, cam, (0.4, 0.8))
    expect = weight * 2.0 + (1.0 - weight) * 3.0
    torch.testing.assert_close(out, torch.full((8, 8), expect), atol=1e-5, rtol=0)


def test_invalid_pixels_and_missing_centre_depth_keep_the_planar_depth() -> None:
    cam = fibonacci_cameras(1, distance=3.0, size=8)[0]
    planar = torch.full((8, 8), 2.0)
    centre = torch.full((8, 8), 3.0)
    centre[0] = 0.0  # no splat centre there
    valid = torch.ones(8, 8, dtype=torch.bool)
    valid[:, 0] = False
    out = grazing_blend(planar, valid, centre, _normal_at(cam, 0.1), cam, (0.4, 0.8))
    assert torch.equal(out[0], planar[0]) and torch.equal(out[:, 0], planar[:, 0])
    torch.testing.assert_close(out[1:, 1:], centre[1:, 1:])
    # a zero normal (nothing rendered) counts as fully oblique, never NaN
    out0 = grazing_blend(planar, valid, centre, torch.zeros(8, 8, 3), cam, (0.4, 0.8))
    assert torch.isfinite(out0).all()
    for bad in ((0.8, 0.4), (-0.1, 0.5), (0.5, 1.5), (0.5, 0.5)):
        with pytest.raises(ValueError, match="cos_range"):
            grazing_blend(planar, valid, centre, _normal_at(cam, 0.5), cam, bad)
