"""Builders shared by the stability tests: cameras, single planar Gaussians, scenes."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from core.render.raster import available_backends
from core.scene.cameras import Camera, Intrinsics
from core.scene.views import Scene, View

# The oracle always; the compiled CPU backend too when it is registered and can run.
BACKENDS: list[str] = ["reference"] + (["cpu"] if "cpu" in available_backends("cpu") else [])

SIZE = 24


def camera(size: int = SIZE, f: float | None = None) -> Camera:
    """Camera at the origin looking down +z (world = camera frame), centred principal point."""
    f = float(size) if f is None else f
    return Camera(
        Intrinsics(f, f, size / 2.0, size / 2.0, size, size), torch.eye(4, dtype=torch.float64)
    )


def quat_axis_angle(axis: tuple[float, float, float], deg: float, dtype=torch.float64) -> Tensor:
    """(1, 4) wxyz quaternion of a rotation by ``deg`` about ``axis``."""
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    h = math.radians(deg) / 2.0
    q = torch.cat([torch.tensor([math.cos(h)], dtype=torch.float64), math.sin(h) * a])
    return q[None].to(dtype)


def rotmat(q: Tensor) -> Tensor:
    """(3, 3) float64 rotation of a unit wxyz quaternion (1, 4)."""
    w, x, y, z = q[0].double().tolist()
    return torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )


def all_finite(*tensors: Tensor | None) -> bool:
    return all(t is None or bool(torch.isfinite(t).all()) for t in tensors)


def scaled_scene(scene: Scene, k: float) -> Scene:
    """The same capture in other units: every length (poses, bounds) times ``k``."""

    def view(v: View) -> View:
        w2c = v.camera.world_to_cam.clone()
        w2c[:3, 3] *= k
        cam = Camera(v.camera.intrinsics, w2c, v.camera.name, dict(v.camera.meta))
        return View(cam, v.image, v.mask, v.name, v.path)

    return Scene(
        train=[view(v) for v in scene.train],
        test=[view(v) for v in scene.test],
        center=scene.center * k,
        radius=scene.radius * k,
        format=scene.format,
        meta=dict(scene.meta),
    )


def replace_views(scene: Scene, train: list[View], test: list[View] | None = None) -> Scene:
    return Scene(
        train=train,
        test=list(scene.test if test is None else test),
        center=scene.center,
        radius=scene.radius,
        format=scene.format,
        meta=dict(scene.meta),
    )


# A training run small enough for CI: 24×24 images, 30 iterations, every phase reached
# (the 30k marks scale to 3 / 7 / 10), densification on, checkpoints every 10.
TINY_TRAIN: dict = {
    "iterations": 30,
    "init_points": 200,
    "envmap_resolution": 8,
    "checkpoint_every": 10,
    "eval": {"every": 10, "views": 1},
    "densify": {"max_gaussians": 800},
}
