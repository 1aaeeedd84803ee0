"""A picture of a mesh, drawn on the server without a display (no OpenGL, no window).

The report shows the extracted surface shaded by its normals and by its vertex colour,
from two viewpoints. Drawing is point splatting with a z-buffer: the surface is
sampled uniformly by area (a few points per output pixel), each sample is projected
and the nearest one per pixel wins. That is exact enough for a preview, needs only
torch, and costs well under a second at 320² for meshes of a few 100k faces.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import trimesh
from PIL import Image
from torch import Tensor

from core.scene.cameras import Camera, Intrinsics

SAMPLES_PER_PIXEL = 12  # surface samples per output pixel (both sides of the object)
CHUNK = 200_000  # samples drawn and splatted at once
BACKGROUND = 1.0  # white


def preview_cameras(mesh: trimesh.Trimesh, size: int) -> list[Camera]:
    """Two views of the mesh's bounding sphere: front-left from above, back-right."""
    lo, hi = mesh.bounds
    center = (lo + hi) / 2.0
    radius = max(float(np.linalg.norm(mesh.vertices - center, axis=1).max()), 1e-6)
    fov = math.radians(40.0)
    dist = radius / math.sin(fov / 2.0) * 1.02
    f = 0.5 * size / math.tan(fov / 2.0)
    intr = Intrinsics(f, f, size / 2.0, size / 2.0, size, size)
    # the scene's "up" is unknown: +z if the mesh is taller along z, else +y
    up = np.array([0.0, 0.0, 1.0]) if (hi - lo)[2] >= (hi - lo)[1] else np.array([0.0, 1.0, 0.0])
    side = np.array([1.0, 0.0, 0.0])
    fwd = np.cross(up, side)
    cams = []
    for az in (math.radians(35.0), math.radians(215.0)):
        d = math.cos(az) * fwd + math.sin(az) * side
        eye = center + dist * (0.9 * d + 0.45 * up) / math.hypot(0.9, 0.45)
        cams.append(Camera.look_at(eye.tolist(), center.tolist(), up.tolist(), intr))
    return cams


def _sample(mesh: trimesh.Trimesh, n: int, rng: np.random.Generator) -> tuple[Tensor, ...]:
    """(points, face normals, colours in [0, 1]) of ``n`` samples uniform by area, float32."""
    v = np.asarray(mesh.vertices, dtype=np.float32)
    f = np.asarray(mesh.faces)
    areas = np.asarray(mesh.area_faces, dtype=np.float64)
    face = rng.choice(len(f), size=n, p=areas / areas.sum())
    r1, r2 = rng.random(n, dtype=np.float32), rng.random(n, dtype=np.float32)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], 1)  # barycentric weights
    tri = f[face]
    pts = np.einsum("nk,nkc->nc", w, v[tri])
    normals = np.asarray(mesh.face_normals, dtype=np.float32)[face]
    vc = getattr(mesh.visual, "vertex_colors", None)
    if vc is not None and len(vc) == len(v):
        rgb = np.asarray(vc, dtype=np.float32)[:, :3] / 255.0
        colors = np.einsum("nk,nkc->nc", w, rgb[tri])
    else:
        colors = np.full((n, 3), 0.7, dtype=np.float32)
    return torch.from_numpy(pts), torch.from_numpy(normals), torch.from_numpy(colors)


class _Canvas:
    """Z-buffer and the two images of one viewpoint, filled chunk by chunk."""

    def __init__(self, camera: Camera) -> None:
        self.camera = camera
        n = camera.height * camera.width
        self.zbuf = torch.full((n,), float("inf"))
        self.normal = torch.full((n, 3), BACKGROUND)
        self.color = torch.full((n, 3), BACKGROUND)

    def splat(self, pts: Tensor, normals: Tensor, colors: Tensor) -> None:
        cam = self.camera
        H, W = cam.height, cam.width
        uv, z = cam.project(pts)
        z = z.float()
        u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        ok = (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        pix = (v * W + u)[ok]
        z, n, c, p = z[ok], normals[ok], colors[ok], pts[ok]
        self.zbuf.scatter_reduce_(0, pix, z, reduce="amin")
        front = z <= self.zbuf[pix]  # nearest so far (a later chunk may still win)
        pix, n, c, p = pix[front], n[front], c[front], p[front]
        view = cam.center.to(p) - p
        view = view / view.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        facing = (n * view).sum(-1, keepdim=True)
        n = torch.where(facing < 0, -n, n)  # both sides of an open surface are drawn lit
        self.normal[pix] = n * 0.5 + 0.5
        self.color[pix] = (c * (0.3 + 0.7 * facing.abs())).clamp(0, 1)

    def images(self) -> np.ndarray:
        H, W = self.camera.height, self.camera.width
        return torch.cat([self.normal.reshape(H, W, 3), self.color.reshape(H, W, 3)], 1).numpy()


def render_mesh_preview(mesh: trimesh.Trimesh, path: str | Path, size: int = 320) -> Path:
    """A 2 × 2 PNG: rows are the two viewpoints, columns normal shading and colour.

    Colours are the mesh's vertex colours as stored (sRGB bytes), so the picture shows
    what a viewer of mesh.glb sees.
    """
    path = Path(path)
    rows = []
    if len(mesh.faces) == 0:
        tile = np.full((size, size, 3), BACKGROUND)
        rows = [np.concatenate([tile, tile], 1)] * 2
    else:
        canvases = [_Canvas(cam) for cam in preview_cameras(mesh, size)]
        rng = np.random.default_rng(0)
        left = SAMPLES_PER_PIXEL * size * size
        while left > 0:  # in chunks: memory stays at one chunk's samples
            chunk = _sample(mesh, min(left, CHUNK), rng)
            for canvas in canvases:
                canvas.splat(*chunk)
            left -= CHUNK
        rows = [canvas.images() for canvas in canvases]
    img = (np.concatenate(rows, 0) * 255.0 + 0.5).clip(0, 255).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    Image.fromarray(img, "RGB").save(tmp, "PNG")
    tmp.replace(path)
    return path
