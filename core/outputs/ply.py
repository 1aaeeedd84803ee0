"""Gaussians ↔ the standard 3DGS PLY layout (binary little-endian, one ``vertex`` element).

Properties, all float32, in this order (3DGS ``save_ply``)::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..44  opacity  scale_0..2  rot_0..3  refl_logit
    [rough_logit]

* ``opacity`` is the logit, ``scale_*`` the log scale, ``rot_*`` the raw (w, x, y, z)
  quaternion: the unconstrained parameters themselves, so a round trip is bit-exact.
* ``f_rest`` is channel-major: 3DGS transposes (N, 15, 3) to (N, 3, 15) and flattens,
  so ``f_rest_0..14`` are the red coefficients of degrees 1..3, then green, then blue.
* ``nx ny nz`` hold the Eq. 6 normal (unoriented). 3DGS writes zeros there and no
  reader uses them for rendering, so either is valid; ours lets point-cloud tools
  show the surface orientation.
* ``refl_logit`` (w_r = sigmoid) is an extra property; 3DGS viewers ignore unknown
  properties. Files without it import with w_r = ``default_refl``.
* ``rough_logit`` (roughness ρ = sigmoid, ``core.render.roughness``) is written only
  for a model that has a roughness, after ``refl_logit``; a file with it imports with
  it, a file without it (any 3DGS file, or ours from before) as a model without one
  (a mirror lookup).

Import also accepts fewer ``f_rest`` (degrees 0..2); the missing coefficients are zero.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from core.errors import SceneError
from core.model.checkpoint import atomic_write
from core.render.gaussians import Gaussians, scalar_logit
from core.render.roughness import ROUGH_KEY, has_roughness
from core.render.sh import MAX_SH_DEGREE, num_sh_bases, sh_degree_from_bases

N_REST = num_sh_bases(MAX_SH_DEGREE) - 1  # 15 coefficients per channel
# A plain 3DGS file has no reflection strength: next to nothing, so it renders as
# it does in a 3DGS viewer, yet the logit stays finite.
DEFAULT_IMPORT_REFL = 1e-4


def ply_property_names(
    n_rest: int = N_REST, with_refl: bool = True, with_rough: bool = False
) -> list[str]:
    """Property names in file order for ``n_rest`` coefficients per channel."""
    names = ["x", "y", "z", "nx", "ny", "nz"]
    names += [f"f_dc_{i}" for i in range(3)]
    names += [f"f_rest_{i}" for i in range(3 * n_rest)]
    names += ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    if with_refl:
        names.append("refl_logit")
    if with_rough:
        names.append("rough_logit")
    return names


def gaussians_to_array(g: Gaussians) -> np.ndarray:
    """The structured vertex array of the 3DGS layout (float32 fields)."""
    p = {k: v.detach().to("cpu", torch.float32) for k, v in g.params.items()}
    n = g.num
    f_dc = p["sh_dc"].transpose(1, 2).reshape(n, 3)
    f_rest = p["sh_rest"].transpose(1, 2).reshape(n, 3 * N_REST)  # channel-major
    with torch.no_grad():
        normals = g.normals().detach().to("cpu", torch.float32)
    rough = has_roughness(g)
    cols = torch.cat(
        [
            p["means"],
            normals,
            f_dc,
            f_rest,
            p["opacity_logits"][:, None],
            p["log_scales"],
            p["quats"],
            p["refl_logits"][:, None],
            *([p[ROUGH_KEY][:, None]] if rough else []),
        ],
        dim=1,
    ).numpy()
    names = ply_property_names(with_rough=rough)
    arr = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        arr[name] = cols[:, i]
    return arr


def save_ply(g: Gaussians, path: str | Path) -> Path:
    """Write ``g`` as a binary little-endian 3DGS PLY (atomically: temp file + rename).

    Refuses (``ValueError`` naming the parameter) to export NaN/Inf: viewers would
    render garbage and :func:`load_ply` rejects such files.
    """
    path = Path(path)
    for name, p in g.params.items():
        if not bool(torch.isfinite(p.detach()).all()):
            raise ValueError(f"{path}: parameter '{name}' holds NaN/Inf; refusing to export")
    el = PlyElement.describe(gaussians_to_array(g), "vertex")
    ply = PlyData([el], text=False, byte_order="<")
    atomic_write(path, ply.write)
    return path


def _field(vertex: PlyElement, name: str, path: Path) -> np.ndarray:
    try:
        col = np.asarray(vertex[name])
    except (KeyError, ValueError) as e:
        raise SceneError("missing property in the 'vertex' element", file=path, field=name) from e
    if col.dtype.kind not in "fiu":
        raise SceneError(f"property has non-numeric type {col.dtype}", file=path, field=name)
    col = col.astype(np.float32, copy=False)
    if not np.isfinite(col).all():
        bad = int((~np.isfinite(col)).sum())
        raise SceneError(f"{bad} value(s) are NaN or Inf", file=path, field=name)
    return col


def load_ply(
    path: str | Path,
    device: torch.device | str = "cpu",
    *,
    default_refl: float = DEFAULT_IMPORT_REFL,
) -> Gaussians:
    """Read a 3DGS-layout PLY (ours or any 3DGS tool's) into :class:`Gaussians`.

    float32 properties come back bit-exactly. ``sh_degree`` follows the number of
    ``f_rest`` properties. Missing or non-finite properties raise
    :class:`SceneError` naming the file and the property.
    """
    path = Path(path)
    try:
        ply = PlyData.read(str(path))
    except FileNotFoundError as e:
        raise SceneError("file not found", file=path) from e
    except Exception as e:  # plyfile raises several types for malformed input
        raise SceneError(f"not a readable PLY file ({e})", file=path) from e
    if "vertex" not in ply:
        raise SceneError("no 'vertex' element", file=path, field="vertex")
    vertex = ply["vertex"]
    names = [prop.name for prop in vertex.properties]

    rest = sorted(
        (int(m.group(1)) for nm in names if (m := re.fullmatch(r"f_rest_(\d+)", nm))),
    )
    if rest != list(range(len(rest))):
        first_gap = next(i for i, r in enumerate([*rest, -1]) if r != i)
        raise SceneError(
            "f_rest properties are not numbered 0..M-1", file=path, field=f"f_rest_{first_gap}"
        )
    if len(rest) % 3:
        raise SceneError(
            f"{len(rest)} f_rest properties is not a multiple of 3", file=path, field="f_rest"
        )
    n_rest = len(rest) // 3
    try:
        sh_degree = sh_degree_from_bases(n_rest + 1)
    except ValueError as e:
        raise SceneError(str(e), file=path, field="f_rest") from e

    def cols(*fields: str) -> torch.Tensor:
        arr = np.stack([_field(vertex, f, path) for f in fields], axis=1)
        return torch.from_numpy(np.ascontiguousarray(arr))

    n = len(vertex.data)
    sh_rest = torch.zeros(n, N_REST, 3, dtype=torch.float32)
    if n_rest:
        flat = cols(*(f"f_rest_{i}" for i in range(3 * n_rest)))
        sh_rest[:, :n_rest, :] = flat.reshape(n, 3, n_rest).transpose(1, 2)
    if "refl_logit" in names:
        refl = cols("refl_logit")[:, 0]
    else:
        refl = torch.full((n,), scalar_logit(default_refl), dtype=torch.float32)
    params = {
        "means": cols("x", "y", "z"),
        "log_scales": cols("scale_0", "scale_1", "scale_2"),
        "quats": cols("rot_0", "rot_1", "rot_2", "rot_3"),
        "opacity_logits": cols("opacity")[:, 0],
        "sh_dc": cols("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :],
        "sh_rest": sh_rest,
        "refl_logits": refl,
    }
    if "rough_logit" in names:
        params[ROUGH_KEY] = cols("rough_logit")[:, 0]
    return Gaussians({k: v.to(device) for k, v in params.items()}, sh_degree=sh_degree)
