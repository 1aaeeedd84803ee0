"""The asset's mesh: simplified to a face budget, UV-unwrapped with xatlas, with
per-vertex tangents for the normal map.

Why xatlas: it packs charts into a square atlas at the texture size with a gutter,
which keeps bilinear taps and mip levels of one chart from reading its neighbours.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from core.errors import AssetError


@dataclass
class UVMesh:
    """A triangle mesh whose vertices carry one UV each (seams split vertices).

    ``uvs`` follow glTF: origin at the image's top-left corner, v down, in [0, 1].
    ``tangents`` (V, 4): xyz along +u, w the handedness such that the bitangent
    cross(normal, tangent)·w points along −v (up in the image; glTF's normal-map +Y).
    """

    positions: np.ndarray  # (V, 3) float32
    normals: np.ndarray  # (V, 3) float32, unit
    uvs: np.ndarray  # (V, 2) float32
    faces: np.ndarray  # (F, 3) uint32
    tangents: np.ndarray  # (V, 4) float32
    source_vertex: np.ndarray  # (V,) index into the simplified mesh's vertices


def simplify_to_budget(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    """Quadric decimation to at most ``faces`` faces (unchanged when already under)."""
    if len(mesh.faces) == 0:
        raise AssetError("the mesh has no faces: the run's surface could not be extracted")
    if faces < 100:
        raise AssetError(f"face budget {faces} is too small; expected at least 100")
    if len(mesh.faces) <= faces:
        return mesh
    out = mesh.simplify_quadric_decimation(face_count=int(faces))
    # decimation lands near the target; a second pass when it overshoots by >2%
    if len(out.faces) > faces * 1.02:
        out = out.simplify_quadric_decimation(face_count=int(faces * 0.97))
    if len(out.faces) == 0 or len(out.faces) > faces * 1.05:
        raise AssetError(
            f"could not simplify the mesh from {len(mesh.faces)} to about {faces} faces "
            f"(got {len(out.faces)}); raise the face budget"
        )
    return out


def unwrap(mesh: trimesh.Trimesh, texture_size: int, padding: int = 4) -> UVMesh:
    """UV atlas of ``mesh`` for a ``texture_size``² texture (``padding`` texels between
    charts), with the mesh's smooth vertex normals and tangents."""
    import xatlas

    mesh = clean_for_unwrap(mesh)
    positions = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    indices = np.ascontiguousarray(mesh.faces, dtype=np.uint32)
    atlas = xatlas.Atlas()
    atlas.add_mesh(positions, indices)
    chart = xatlas.ChartOptions()
    pack = xatlas.PackOptions()
    pack.resolution = int(texture_size)
    pack.padding = int(padding)
    pack.bilinear = True
    pack.blockAlign = True
    atlas.generate(chart, pack)
    vmap, faces, uvs = atlas[0]
    vnormals = unit_vertex_normals(mesh)
    out_pos = positions[vmap]
    out_nrm = vnormals[vmap]
    uvs = np.asarray(uvs, dtype=np.float32)
    uvs = np.stack([uvs[:, 0], 1.0 - uvs[:, 1]], 1)  # xatlas: v up; glTF: v down
    faces = np.asarray(faces, dtype=np.uint32)
    tangents = vertex_tangents(out_pos, out_nrm, uvs, faces)
    return UVMesh(out_pos, out_nrm, uvs, faces, tangents, np.asarray(vmap, dtype=np.int64))


def clean_for_unwrap(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Without zero-area faces and unreferenced vertices (their normals are undefined)."""
    out = mesh.copy()
    out.update_faces(out.nondegenerate_faces(height=1e-12))
    out.remove_unreferenced_vertices()
    if len(out.faces) == 0:
        raise AssetError("the mesh has only degenerate faces; nothing to texture")
    return out


def unit_vertex_normals(mesh: trimesh.Trimesh) -> np.ndarray:
    """Area-weighted vertex normals, unit length everywhere (glTF requires it): where
    the weighted sum cancels, the plain mean of the faces' normals, else +Z."""
    n = np.asarray(mesh.vertex_normals, dtype=np.float64)
    raw = np.zeros_like(n)
    fn = np.asarray(mesh.face_normals, dtype=np.float64)
    for k in range(3):
        np.add.at(raw, mesh.faces[:, k], fn)
    length = np.linalg.norm(n, axis=1)
    n = np.where((length > 0.5)[:, None], n, raw)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 1e-9, n / np.maximum(length, 1e-12), [[0.0, 0.0, 1.0]])
    return n.astype(np.float32)


def face_frames(
    positions: np.ndarray, uvs: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per face dP/du and dP/d(−v) (glTF v points down; −v is up in the image)."""
    p = positions[faces].astype(np.float64)
    t = uvs[faces].astype(np.float64)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    inv = np.where(np.abs(det) > 1e-20, 1.0 / np.where(det == 0, 1.0, det), 0.0)[:, None]
    dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * inv
    dpdv = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * inv
    return dpdu, -dpdv


def vertex_tangents(
    positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray, faces: np.ndarray
) -> np.ndarray:
    """Per-vertex glTF tangents (V, 4): face dP/du summed over a vertex's faces,
    Gram–Schmidt against the normal; w = ±1 so that cross(n, t)·w ≈ dP/d(−v)."""
    dpdu, dpdup = face_frames(positions, uvs, faces)
    n_v = len(positions)
    t_sum = np.zeros((n_v, 3))
    b_sum = np.zeros((n_v, 3))
    for k in range(3):
        np.add.at(t_sum, faces[:, k], dpdu)
        np.add.at(b_sum, faces[:, k], dpdup)
    n = normals.astype(np.float64)
    t = t_sum - n * np.sum(t_sum * n, 1, keepdims=True)
    norm = np.linalg.norm(t, axis=1, keepdims=True)
    # degenerate UVs: any unit vector orthogonal to the normal
    fallback = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    fallback /= np.maximum(np.linalg.norm(fallback, axis=1, keepdims=True), 1e-12)
    t = np.where(norm > 1e-12, t / np.maximum(norm, 1e-12), fallback)
    w = np.where(np.sum(np.cross(n, t) * b_sum, 1) < 0.0, -1.0, 1.0)
    return np.concatenate([t, w[:, None]], 1).astype(np.float32)
