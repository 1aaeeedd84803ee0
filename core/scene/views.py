"""The one in-memory scene every loader produces and every consumer reads."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from core.scene.cameras import Camera


@dataclass
class View:
    """One posed image.

    ``image`` is (H, W, 3) float32 in linear light, [0, 1] for LDR sources.
    ``mask`` is (H, W) float32 in [0, 1] (object coverage) or ``None`` when the
    source carries no alpha or mask. RGB is straight (not premultiplied).
    """

    camera: Camera
    image: Tensor
    mask: Tensor | None = None
    name: str = ""
    path: Path | None = None

    @property
    def height(self) -> int:
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    def composited(self, background: Tensor) -> Tensor:
        """Image over ``background`` (3,) using the mask as alpha (the training target)."""
        if self.mask is None:
            return self.image
        a = self.mask[..., None]
        return self.image * a + background.to(self.image) * (1.0 - a)


@dataclass
class Scene:
    """Cameras, images, masks and split of one capture, in OpenCV world conventions.

    ``center``/``radius`` bound the region of interest (the object); they drive
    random initialisation, learning-rate scaling and mesh extraction bounds.
    ``points``/``point_colors`` are an optional sparse cloud (COLMAP) for init.
    """

    train: list[View]
    test: list[View]
    center: Tensor
    radius: float
    format: str
    root: Path | None = None
    points: Tensor | None = None
    point_colors: Tensor | None = None
    meta: dict = field(default_factory=dict)

    @property
    def views(self) -> list[View]:
        return self.train + self.test

    @property
    def has_masks(self) -> bool:
        return any(v.mask is not None for v in self.views)

    @property
    def cameras(self) -> list[Camera]:
        return [v.camera for v in self.views]

    def summary(self) -> dict:
        """A JSON-able description (used by validation reports and the API)."""
        first = self.views[0]
        i = first.camera.intrinsics
        sizes = sorted({(v.width, v.height) for v in self.views})
        return {
            "format": self.format,
            "train_views": len(self.train),
            "test_views": len(self.test),
            "resolutions": [list(s) for s in sizes],
            "intrinsics_first": {"fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy},
            "masks": self.has_masks,
            "center": [float(x) for x in self.center],
            "radius": float(self.radius),
            "points": 0 if self.points is None else int(self.points.shape[0]),
            "warnings": list(self.meta.get("warnings", [])),
        }


def bounds_from_cameras(cameras: list[Camera]) -> tuple[Tensor, float]:
    """Centre and radius of the object from camera geometry alone.

    The centre is the least-squares point closest to all optical axes (cameras of an
    object capture look at it); the radius is half the median camera distance to it,
    a conservative bound for objects that fill a good part of the frame. Colinear or
    single-view rigs fall back to the point one median distance ahead of the cameras.
    """
    centers = torch.stack([c.center for c in cameras])
    dirs = torch.stack([c.forward for c in cameras])
    eye = torch.eye(3, dtype=torch.float64)
    A = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.zeros(3, dtype=torch.float64)
    for o, d in zip(centers, dirs, strict=True):
        P = eye - torch.outer(d, d)
        A += P
        b += P @ o
    cond = torch.linalg.cond(A)
    if len(cameras) >= 2 and torch.isfinite(cond) and cond < 1e6:
        center = torch.linalg.solve(A, b)
    else:
        spread = (centers - centers.mean(0)).norm(dim=-1).max()
        step = float(spread) if float(spread) > 0 else 1.0
        center = (centers + dirs * step).mean(0)
    dist = (centers - center).norm(dim=-1)
    radius = float(dist.median()) * 0.5
    if not radius > 0:
        radius = 1.0
    return center, radius
