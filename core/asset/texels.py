"""Texels of a UV atlas as surface samples: which face covers each texel centre, where
on the surface it is, and its shading frame; and gutter filling after baking.

The rasteriser is a numba loop over faces (edge functions on each face's UV bounding
box): the atlas has up to millions of texels and hundreds of thousands of faces.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from core.asset.uv_mesh import UVMesh


@dataclass
class TexelSamples:
    """Covered texels (M of them) of a size×size atlas and their surface samples."""

    size: int
    rows: np.ndarray  # (M,) int64, image row (top = 0)
    cols: np.ndarray  # (M,) int64
    face: np.ndarray  # (M,) int64
    points: np.ndarray  # (M, 3) float32, world position
    normals: np.ndarray  # (M, 3) float32, unit interpolated mesh normal
    tangents: np.ndarray  # (M, 3) float32, unit, along +u, orthogonal to the normal
    bitangents: np.ndarray  # (M, 3) float32, unit, along −v (up in the image)

    @property
    def count(self) -> int:
        return len(self.rows)

    def to_image(self, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """Scatter per-texel values (M, C) into a (size, size, C) image."""
        values = values.reshape(self.count, -1)
        img = np.full((self.size, self.size, values.shape[1]), fill, dtype=np.float32)
        img[self.rows, self.cols] = values
        return img

    def mask(self, select: np.ndarray | None = None) -> np.ndarray:
        """(size, size) bool: the covered texels, or those of them where ``select`` (M,)."""
        m = np.zeros((self.size, self.size), dtype=bool)
        if select is None:
            m[self.rows, self.cols] = True
        else:
            m[self.rows[select], self.cols[select]] = True
        return m


@numba.njit(cache=True)
def _raster(uv_px: np.ndarray, faces: np.ndarray, size: int):  # pragma: no cover - numba
    owner = np.full((size, size), -1, dtype=np.int64)
    b1 = np.zeros((size, size), dtype=np.float32)
    b2 = np.zeros((size, size), dtype=np.float32)
    for f in range(faces.shape[0]):
        ax, ay = uv_px[faces[f, 0], 0], uv_px[faces[f, 0], 1]
        bx, by = uv_px[faces[f, 1], 0], uv_px[faces[f, 1], 1]
        cx, cy = uv_px[faces[f, 2], 0], uv_px[faces[f, 2], 1]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if abs(area) < 1e-12:
            continue
        x0 = max(int(np.floor(min(ax, bx, cx) - 0.5)), 0)
        x1 = min(int(np.ceil(max(ax, bx, cx) - 0.5)), size - 1)
        y0 = max(int(np.floor(min(ay, by, cy) - 0.5)), 0)
        y1 = min(int(np.ceil(max(ay, by, cy) - 0.5)), size - 1)
        for y in range(y0, y1 + 1):
            py = y + 0.5
            for x in range(x0, x1 + 1):
                px = x + 0.5
                w1 = ((px - ax) * (cy - ay) - (py - ay) * (cx - ax)) / area
                w2 = ((bx - ax) * (py - ay) - (by - ay) * (px - ax)) / area
                w0 = 1.0 - w1 - w2
                if w0 >= -1e-6 and w1 >= -1e-6 and w2 >= -1e-6:
                    owner[y, x] = f
                    b1[y, x] = w1
                    b2[y, x] = w2
    return owner, b1, b2


def rasterize_atlas(mesh: UVMesh, size: int) -> TexelSamples:
    """The covered texel centres of the atlas and their surface samples."""
    uv_px = (mesh.uvs.astype(np.float64) * size).astype(np.float64)
    owner, b1, b2 = _raster(uv_px, mesh.faces.astype(np.int64), int(size))
    rows, cols = np.nonzero(owner >= 0)
    face = owner[rows, cols]
    w1, w2 = b1[rows, cols][:, None], b2[rows, cols][:, None]
    w0 = 1.0 - w1 - w2
    tri = mesh.faces[face].astype(np.int64)
    pos = mesh.positions
    points = w0 * pos[tri[:, 0]] + w1 * pos[tri[:, 1]] + w2 * pos[tri[:, 2]]
    nrm = mesh.normals
    normals = w0 * nrm[tri[:, 0]] + w1 * nrm[tri[:, 1]] + w2 * nrm[tri[:, 2]]
    normals = _unit(normals)
    # the shading frame the normal map is read in: the interpolated vertex tangent
    tan = mesh.tangents
    t = w0 * tan[tri[:, 0], :3] + w1 * tan[tri[:, 1], :3] + w2 * tan[tri[:, 2], :3]
    t = _unit(t - normals * np.sum(t * normals, 1, keepdims=True))
    sign = np.where(tan[tri[:, 0], 3] < 0, -1.0, 1.0)[:, None]
    b = np.cross(normals, t) * sign
    return TexelSamples(
        size=int(size),
        rows=rows.astype(np.int64),
        cols=cols.astype(np.int64),
        face=face.astype(np.int64),
        points=points.astype(np.float32),
        normals=normals.astype(np.float32),
        tangents=t.astype(np.float32),
        bitangents=b.astype(np.float32),
    )


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


def fill_unknown(image: np.ndarray, known: np.ndarray, iterations: int = 16) -> np.ndarray:
    """Spread known texels into unknown ones (gutters, unseen texels): each pass gives
    an unknown texel the mean of its known 8-neighbours; what is left after
    ``iterations`` passes gets the mean of all known texels. Keeps bilinear taps and
    mip levels at chart borders from reading black."""
    img = image.astype(np.float32).copy()
    if img.ndim == 2:
        img = img[..., None]
    k = known.copy()
    if not k.any():
        return img if image.ndim == 3 else img[..., 0]
    for _ in range(iterations):
        if k.all():
            break
        acc = np.zeros_like(img)
        cnt = np.zeros(k.shape, dtype=np.float32)
        kp = np.pad(k, 1)
        ip = np.pad(img * k[..., None], ((1, 1), (1, 1), (0, 0)))
        h, w = k.shape
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy == 0 and dx == 0:
                    continue
                acc += ip[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
                cnt += kp[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
        new = (~k) & (cnt > 0)
        img[new] = acc[new] / cnt[new][:, None]
        k = k | new
    if not k.all():
        img[~k] = img[k].mean(0)
    return img if image.ndim == 3 else img[..., 0]
