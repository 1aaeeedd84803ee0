"""Camera rays are computed once per intrinsics, dtype and device, and are the rays."""

from __future__ import annotations

import torch

from core.scene.cameras import Camera, Intrinsics


def test_rays_are_k_inverse_of_pixel_centres_and_shared_between_equal_cameras():
    intr = Intrinsics(50.0, 40.0, 15.5, 11.0, 32, 24)
    a = Camera.look_at([0.0, -3.0, 1.0], [0, 0, 0], [0, 0, 1], intr)
    same = Intrinsics(50.0, 40.0, 15.5, 11.0, 32, 24)  # equal, not the same object
    b = Camera.look_at([2.0, 2.0, 2.0], [0, 0, 0], [0, 0, 1], same)
    rays = a.camera_rays(torch.float64)
    assert rays.shape == (24, 32, 3) and rays.dtype == torch.float64
    j, i = 7, 20  # pixel row 7, column 20: centre (20.5, 7.5)
    want = torch.tensor([(20.5 - 15.5) / 50.0, (7.5 - 11.0) / 40.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(rays[j, i], want, rtol=0, atol=1e-15)
    assert b.camera_rays(torch.float64) is rays  # same intrinsics, another pose: shared
    assert a.camera_rays(torch.float32).dtype == torch.float32
    other = Camera(Intrinsics(50.0, 40.0, 16.0, 11.0, 32, 24), a.world_to_cam)
    assert not torch.equal(other.camera_rays(torch.float64), rays)
    # world rays still come from them: unit length, through the pixel
    origin, dirs = a.world_rays(torch.float64)
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones(24, 32, dtype=torch.float64))
    pix, _ = a.project(origin + 2.0 * dirs[j, i])
    torch.testing.assert_close(pix, torch.tensor([20.5, 7.5], dtype=torch.float64))
