"""Ambient occlusion of the mesh at texel points: the cosine-weighted fraction of the
hemisphere around the normal that escapes the mesh.

Glint's base colour has the shadowing of concave parts baked in; a path tracer adds
it again, so the material divides it out (core.asset.material) and the asset carries
it as glTF's occlusion map for rasterisers. Rays run on Embree (embreex) through
trimesh; without it the asset has no occlusion map and says so.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import trimesh

RAYS_PER_CHUNK = 1 << 20


def embree_available() -> bool:
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector  # noqa: F401
    except Exception:  # ImportError, or embreex failing to load its library
        return False
    return True


def hemisphere_directions(normals: np.ndarray, rays: int, seed: int = 0) -> np.ndarray:
    """(N, rays, 3) cosine-weighted directions about unit normals (N, 3), stratified
    over a rays-point Fibonacci spiral on the disc (the same pattern per texel, turned
    by a random angle each, so neighbouring texels do not band)."""
    rng = np.random.default_rng(seed)
    k = np.arange(rays) + 0.5
    r = np.sqrt(k / rays)
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    turn = rng.uniform(0, 2 * math.pi, size=(len(normals), 1))
    x = r[None] * np.cos(phi[None] + turn)
    y = r[None] * np.sin(phi[None] + turn)
    z = np.sqrt(np.maximum(0.0, 1.0 - x * x - y * y))
    n = normals.astype(np.float64)
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t = np.cross(n, helper)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(n, t)
    return x[..., None] * t[:, None] + y[..., None] * b[:, None] + z[..., None] * n[:, None]


def ambient_occlusion(
    mesh: trimesh.Trimesh,
    points: np.ndarray,
    normals: np.ndarray,
    *,
    rays: int = 16,
    offset: float | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """AO in [0, 1] (1 = open) at points (N, 3) with unit normals (N, 3)."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    if offset is None:  # off the surface by a small fraction of the object
        offset = 1e-3 * float(np.linalg.norm(mesh.extents))
    hit = RayMeshIntersector(mesh)
    n = len(points)
    per = max(1, RAYS_PER_CHUNK // rays)
    out = np.empty(n, dtype=np.float32)
    for start in range(0, n, per):
        sl = slice(start, min(n, start + per))
        nrm = normals[sl].astype(np.float64)
        dirs = hemisphere_directions(nrm, rays, seed=start)
        origins = points[sl].astype(np.float64) + offset * nrm
        origins = np.repeat(origins[:, None], rays, 1)
        blocked = hit.intersects_any(origins.reshape(-1, 3), dirs.reshape(-1, 3))
        out[sl] = 1.0 - blocked.reshape(-1, rays).mean(1)
        if progress is not None:
            progress(sl.stop, n)
    return out
