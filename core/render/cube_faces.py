"""Cube-map faces: the one table every lookup follows, and the geometry built on it.

Torch code (``core.render.envmap``, ``envmap_mips``) and the compiled lookups
(``shading_compiled``, ``envmap_lookup_compiled``, ``envmap_pack_compiled``) read the
same table, face projection, border plan and mip sizes; this module imports none of
them, so all can import it. (No numba here: numba functions are not shared across
files, since numba's on-disk cache does not notice an edit in another file.)
"""

from __future__ import annotations

from functools import lru_cache

import torch
from torch import Tensor

# Per face: (major axis, major sign, sc axis, sc sign, tc axis, tc sign).
FACE_TABLE: tuple[tuple[int, int, int, int, int, int], ...] = (
    (0, +1, 2, -1, 1, -1),
    (0, -1, 2, +1, 1, -1),
    (1, +1, 0, +1, 2, +1),
    (1, -1, 0, +1, 2, -1),
    (2, +1, 0, +1, 1, -1),
    (2, -1, 0, -1, 1, -1),
)


@lru_cache(maxsize=16)
def _face_tables(device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Per face: component indices of (major, sc, tc) and their signs (6, 3) each."""
    t = torch.tensor(FACE_TABLE, dtype=torch.long)
    return t[:, [0, 2, 4]].to(device), t[:, [1, 3, 5]].to(device=device, dtype=dtype)


def direction_to_face_uv(dirs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Face index (...) long and face coordinates u = sc/ma, v = tc/ma in [-1, 1].

    ``dirs`` need not be unit length but must be finite and non-zero (see
    :func:`sample_cube` for the guarded entry point). Differentiable in ``dirs``.
    """
    with torch.no_grad():
        axis = dirs.abs().argmax(dim=-1, keepdim=True)
        face = (2 * axis + (dirs.gather(-1, axis) < 0).long()).squeeze(-1)
    axes, signs = _face_tables(dirs.device, dirs.dtype)
    # One gather gives (ma, sc, tc) per direction (the major sign makes ma = |d_major|).
    comp = dirs.gather(-1, axes[face]) * signs[face]
    ma = comp[..., 0]
    # |sc|, |tc| <= ma exactly, and IEEE division is monotonic: u, v stay in [-1, 1].
    return face, comp[..., 1] / ma, comp[..., 2] / ma


def face_uv_to_direction(face: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Inverse of :func:`direction_to_face_uv`: the (unnormalised) direction with ma = 1."""
    t = torch.tensor(FACE_TABLE, dtype=torch.long, device=face.device)[face]
    d = torch.zeros((*face.shape, 3), dtype=u.dtype, device=u.device)
    d.scatter_(-1, t[..., 0:1], t[..., 1:2].to(u.dtype))
    d.scatter_(-1, t[..., 2:3], (u * t[..., 3].to(u.dtype)).unsqueeze(-1))
    d.scatter_(-1, t[..., 4:5], (v * t[..., 5].to(u.dtype)).unsqueeze(-1))
    return d


@lru_cache(maxsize=16)
def pad_plan_cpu(resolution: int) -> tuple[Tensor, Tensor, Tensor]:
    """Gather plan for the padded faces (6, R+2, R+2) from the flat texels (6·R·R).

    Returns (source index per padded texel, corner positions (24,), corner sources
    (24, 3)). Border sources are found geometrically: the border texel's centre on the
    face's extended plane is projected onto the cube and the texel it lands in is
    taken; this is the neighbour's edge texel at the same position along the edge.
    """
    r, p = resolution, resolution + 2
    c = (torch.arange(p, dtype=torch.float64) - 0.5) * (2.0 / r) - 1.0  # padded centres
    vv, uu = torch.meshgrid(c, c, indexing="ij")
    face = torch.arange(6).view(6, 1, 1).expand(6, p, p)
    d = face_uv_to_direction(face, uu.expand(6, p, p), vv.expand(6, p, p))
    g, ug, vg = direction_to_face_uv(d)
    col = ((ug + 1.0) * (0.5 * r)).floor().long().clamp(0, r - 1)
    row = ((vg + 1.0) * (0.5 * r)).floor().long().clamp(0, r - 1)
    src = g * r * r + row * r + col  # (6, p, p); corners fixed below

    corner_pos, corner_src = [], []
    for f in range(6):
        for py in (0, p - 1):
            for px in (0, p - 1):
                own = src[f, 1 if py == 0 else p - 2, 1 if px == 0 else p - 2]
                along_row = src[f, py, 1 if px == 0 else p - 2]
                along_col = src[f, 1 if py == 0 else p - 2, px]
                corner_pos.append(f * p * p + py * p + px)
                corner_src.append([int(own), int(along_row), int(along_col)])
    return src.reshape(-1), torch.tensor(corner_pos), torch.tensor(corner_src)


def mip_sizes(resolution: int) -> list[int]:
    """Face size of each level: halved while even, down to 1 (an odd size ends it)."""
    sizes = [int(resolution)]
    while sizes[-1] > 1 and sizes[-1] % 2 == 0:
        sizes.append(sizes[-1] // 2)
    return sizes
