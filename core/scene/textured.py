"""A textured synthetic capture with known cameras, for testing structure from motion.

The analytic scenes of :mod:`core.scene.synthetic` have smooth albedo: SIFT finds
next to nothing on them. Here the object (the same sphere or box) and a surrounding
"room" (a large sphere, so the background has parallax like a real one) carry a
solid texture of random coloured spots, which gives SIFT blobs that stay put on the
surface from every viewpoint. A little mirror reflection on the object adds the
view-dependent highlights a shiny object shows. Cameras walk rings around the object
the way a handheld capture does; images may be non-square.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from torch import Tensor

from core.scene.cameras import Camera, Intrinsics
from core.scene.synthetic import default_env, intersect, irradiance
from core.scene.views import Scene, View

ROOM_RADIUS = 6.0


def cell_texture(points: Tensor, cell: float, seed: int) -> Tensor:
    """Colour (..., 3) in [0, 1]: a random colour per cube of side ``cell`` (hashed).

    Cut by a surface the cubes make irregular patches whose corners SIFT finds, at
    the cost of a few integer operations per point.
    """
    g = torch.Generator().manual_seed(seed)
    palette = torch.rand(4096, 3, generator=g)
    ijk = torch.floor(points / cell).to(torch.int64)
    h = (ijk[..., 0] * 73856093) ^ (ijk[..., 1] * 19349663) ^ (ijk[..., 2] * 83492791)
    return palette[h.remainder(4096)]


def ring_cameras(
    n: int,
    width: int,
    height: int,
    *,
    rings: tuple[float, ...] = (15.0, 40.0),
    distance: float = 3.0,
    fov_x_deg: float = 50.0,
) -> list[Camera]:
    """``n`` cameras on rings (elevations in degrees) at ``distance``, looking at the origin."""
    f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    intr = Intrinsics(f, f, width / 2, height / 2, width, height)
    per = [n // len(rings) + (i < n % len(rings)) for i in range(len(rings))]
    cams = []
    for r, (elev, k) in enumerate(zip(rings, per, strict=True)):
        e = math.radians(elev)
        for i in range(k):
            a = 2 * math.pi * (i + 0.5 * r) / k
            eye = [distance * math.cos(e) * math.cos(a), distance * math.cos(e) * math.sin(a)]
            eye.append(distance * math.sin(e))
            cams.append(
                Camera.look_at(eye, [0, 0, 0], [0, 0, 1], intr, name=f"view_{len(cams):03d}")
            )
    return cams


def _two_scale(points: Tensor, cell: float, seed: int) -> Tensor:
    """Cells of two sizes blended: corners at two scales, none of them repeating."""
    return 0.6 * cell_texture(points, cell, seed) + 0.4 * cell_texture(points, cell / 2.7, seed + 7)


@torch.no_grad()
def render_textured_view(
    camera: Camera, *, shape: str = "sphere", seed: int = 0, reflect: float = 0.15, samples: int = 2
) -> tuple[Tensor, Tensor]:
    """RGB (H, W, 3) in [0, 1] and the object's coverage (H, W) seen from ``camera``,
    averaged over ``samples``² rays per pixel (sharp texture edges would alias)."""
    fine = camera.scaled(samples) if samples > 1 else camera
    o, d = fine.world_rays(torch.float32)
    hit, t, n = intersect(o, d, shape)
    p = o + t[..., None] * d
    obj = _two_scale(p, 0.1, seed) * irradiance(n)
    refl = d - 2.0 * (d * n).sum(-1, keepdim=True) * n
    obj = obj + reflect * default_env(torch.nn.functional.normalize(refl, dim=-1))
    # the room: where a ray leaves the sphere of radius ROOM_RADIUS around the origin
    b = (d * o).sum(-1)
    t_room = -b + (b * b - o @ o + ROOM_RADIUS**2).sqrt()
    room = _two_scale(o + t_room[..., None] * d, 0.6, seed + 1)
    rgb = torch.cat(
        [torch.where(hit[..., None], obj, room).clamp(0, 1), hit[..., None].float()], -1
    )
    if samples > 1:
        rgb = torch.nn.functional.avg_pool2d(rgb.permute(2, 0, 1)[None], samples)[0].permute(
            1, 2, 0
        )
    return rgb[..., :3].contiguous(), rgb[..., 3].contiguous()


def make_textured_scene(
    n_views: int = 24,
    width: int = 160,
    height: int = 120,
    *,
    shape: str = "sphere",
    seed: int = 0,
) -> Scene:
    """``n_views`` textured views on two rings (all train), masks = the object."""
    views = []
    for cam in ring_cameras(n_views, width, height):
        rgb, mask = render_textured_view(cam, shape=shape, seed=seed)
        views.append(View(camera=cam, image=rgb, mask=mask, name=cam.name))
    return Scene(
        train=views,
        test=[],
        center=torch.zeros(3, dtype=torch.float64),
        radius=0.6,
        format="synthetic",
        meta={"warnings": [], "synthetic": {"textured": True, "shape": shape, "seed": seed}},
    )


def write_photos(scene: Scene, folder: str | Path, *, ext: str = ".png") -> dict[str, Tensor]:
    """The views as plain photos (``images/``) and masks (``masks/``) in ``folder``, as a
    user without poses has them; returns each photo stem's true world-to-camera."""
    from core.scene.imageio import write_image

    out = Path(folder)
    truth = {}
    for v in scene.views:
        write_image(out / "images" / f"{v.name}{ext}", v.image)
        write_image(out / "masks" / f"{v.name}.png", v.mask, encode_srgb=False)
        truth[v.name] = v.camera.world_to_cam
    return truth
