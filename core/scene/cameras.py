"""Pinhole cameras in one convention: OpenCV axes, world-to-camera 4×4, general K.

Camera space: x right, y down, z forward. Pixel (i, j) (column, row) has its centre
at (i + 0.5, j + 0.5). Loaders convert other conventions on the way in; nothing
downstream ever sees OpenGL axes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import torch
from torch import Tensor

# OpenGL camera axes (x right, y up, z back) -> OpenCV (x right, y down, z forward).
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels; the principal point is general (not W/2)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def K(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Tensor:
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
            dtype=dtype,
            device=device,
        )

    def scaled(self, factor: float) -> Intrinsics:
        """Intrinsics of the image resized by ``factor`` (pixel edges map to pixel edges)."""
        w = max(1, round(self.width * factor))
        h = max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, w, h)

    @staticmethod
    def from_fov_x(fov_x: float, width: int, height: int) -> Intrinsics:
        """NeRF-synthetic style: focal from the horizontal field of view, centred."""
        f = 0.5 * width / torch.tan(torch.tensor(0.5 * fov_x, dtype=torch.float64)).item()
        return Intrinsics(f, f, width / 2.0, height / 2.0, width, height)


RAY_CACHE_SIZE = 16  # distinct intrinsics × dtype × device kept (a capture has one or a few)


@lru_cache(maxsize=RAY_CACHE_SIZE)
def _camera_rays(intr: Intrinsics, dtype: torch.dtype, device: torch.device) -> Tensor:
    u = torch.arange(intr.width, dtype=dtype, device=device) + 0.5
    v = torch.arange(intr.height, dtype=dtype, device=device) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    x = (uu - intr.cx) / intr.fx
    y = (vv - intr.cy) / intr.fy
    return torch.stack([x, y, torch.ones_like(x)], dim=-1)


@dataclass
class Camera:
    """A posed pinhole camera. ``world_to_cam`` is float64 (4, 4), OpenCV axes."""

    intrinsics: Intrinsics
    world_to_cam: Tensor
    name: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        w2c = torch.as_tensor(self.world_to_cam, dtype=torch.float64).clone()
        if w2c.shape == (3, 4):
            w2c = torch.cat([w2c, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
        if w2c.shape != (4, 4):
            raise ValueError(f"world_to_cam must be 4x4 or 3x4, got {tuple(w2c.shape)}")
        self.world_to_cam = w2c

    # -- basic quantities -------------------------------------------------
    @property
    def width(self) -> int:
        return self.intrinsics.width

    @property
    def height(self) -> int:
        return self.intrinsics.height

    @property
    def R(self) -> Tensor:
        return self.world_to_cam[:3, :3]

    @property
    def t(self) -> Tensor:
        return self.world_to_cam[:3, 3]

    @property
    def center(self) -> Tensor:
        """Camera centre in world coordinates, float64 (3,)."""
        return -self.R.T @ self.t

    @property
    def forward(self) -> Tensor:
        """Optical axis (camera +z) in world coordinates, float64 (3,)."""
        return self.R[2]

    def cam_to_world(self) -> Tensor:
        return torch.linalg.inv(self.world_to_cam)

    def K(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Tensor:
        return self.intrinsics.K(dtype, device)

    def scaled(self, factor: float) -> Camera:
        return replace(self, intrinsics=self.intrinsics.scaled(factor))

    # -- conventions ------------------------------------------------------
    @staticmethod
    def from_opengl_c2w(
        c2w: Tensor, intrinsics: Intrinsics, name: str = "", meta: dict | None = None
    ) -> Camera:
        """From an OpenGL/Blender camera-to-world (camera looks down -z, +y up)."""
        c2w = torch.as_tensor(c2w, dtype=torch.float64)
        if c2w.shape == (3, 4):
            c2w = torch.cat([c2w, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
        c2w_cv = c2w.clone()
        c2w_cv[:3, :3] = c2w[:3, :3] @ _GL_TO_CV
        return Camera(intrinsics, torch.linalg.inv(c2w_cv), name, dict(meta or {}))

    def to_opengl_c2w(self) -> Tensor:
        c2w = self.cam_to_world()
        c2w[:3, :3] = c2w[:3, :3] @ _GL_TO_CV
        return c2w

    @staticmethod
    def look_at(
        eye: Tensor | list[float],
        target: Tensor | list[float],
        up: Tensor | list[float],
        intrinsics: Intrinsics,
        name: str = "",
    ) -> Camera:
        """Camera at ``eye`` looking at ``target``; ``up`` points up in the image."""
        eye = torch.as_tensor(eye, dtype=torch.float64)
        target = torch.as_tensor(target, dtype=torch.float64)
        up = torch.as_tensor(up, dtype=torch.float64)
        z = target - eye
        z = z / z.norm()
        x = torch.linalg.cross(z, up)  # right = forward × up (OpenCV: y = z × x is down)
        if x.norm() < 1e-12:
            raise ValueError("look_at: 'up' is parallel to the viewing direction")
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        R = torch.stack([x, y, z])
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = R
        w2c[:3, 3] = -R @ eye
        return Camera(intrinsics, w2c, name)

    # -- rays and projection ----------------------------------------------
    def pixel_centers(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"
    ) -> Tensor:
        """(H, W, 2) pixel-centre coordinates (u, v) = (i + 0.5, j + 0.5)."""
        u = torch.arange(self.width, dtype=dtype, device=device) + 0.5
        v = torch.arange(self.height, dtype=dtype, device=device) + 0.5
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        return torch.stack([uu, vv], dim=-1)

    def camera_rays(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"
    ) -> Tensor:
        """(H, W, 3) r̃ = K⁻¹(u, v, 1) in camera space: z component exactly 1.

        Depth along r̃ is z-depth, which is what Eq. 8's d = D / (N·r̃) returns. The
        tensor is shared between calls with the same intrinsics (a training step read
        it five times, 0.36 ms each at 128²): callers must not write into it.
        """
        return _camera_rays(self.intrinsics, dtype, torch.device(device))

    def world_rays(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"
    ) -> tuple[Tensor, Tensor]:
        """Origins (3,) and unit world directions (H, W, 3) through pixel centres."""
        d_cam = self.camera_rays(torch.float64, device)
        d = d_cam @ self.R.to(device)  # row-vector form of R^T d
        d = d / d.norm(dim=-1, keepdim=True)
        return self.center.to(device=device, dtype=dtype), d.to(dtype)

    def world_to_camera_points(self, points: Tensor) -> Tensor:
        R = self.R.to(points)
        t = self.t.to(points)
        return points @ R.T + t

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """World points (..., 3) -> pixel coordinates (..., 2) and z-depth (...)."""
        pc = self.world_to_camera_points(points)
        z = pc[..., 2]
        i = self.intrinsics
        u = i.fx * pc[..., 0] / z + i.cx
        v = i.fy * pc[..., 1] / z + i.cy
        return torch.stack([u, v], dim=-1), z

    def backproject(self, uv: Tensor, depth: Tensor) -> Tensor:
        """Pixel coordinates (..., 2) and z-depth (...) -> world points (..., 3)."""
        i = self.intrinsics
        x = (uv[..., 0] - i.cx) / i.fx * depth
        y = (uv[..., 1] - i.cy) / i.fy * depth
        pc = torch.stack([x, y, depth], dim=-1)
        R = self.R.to(pc)
        t = self.t.to(pc)
        return (pc - t) @ R

    def to_dict(self) -> dict:
        i = self.intrinsics
        return {
            "name": self.name,
            "fx": i.fx,
            "fy": i.fy,
            "cx": i.cx,
            "cy": i.cy,
            "width": i.width,
            "height": i.height,
            "world_to_cam": self.world_to_cam.tolist(),
        }

    @staticmethod
    def from_dict(d: dict) -> Camera:
        intr = Intrinsics(d["fx"], d["fy"], d["cx"], d["cy"], int(d["width"]), int(d["height"]))
        return Camera(intr, torch.tensor(d["world_to_cam"], dtype=torch.float64), d.get("name", ""))
