"""Environment maps in and out: EXR cube cross, EXR lat-long, PNG preview.

Cube cross (horizontal, 4R wide × 3R tall, float EXR; unused blocks are 0)::

            [+Y]
      [-X]  [+Z]  [+X]  [-Z]
            [-Y]

Each face is placed exactly as stored (row = t, column = s; see ``core.render.envmap``), which
makes the cross fold into the cube with matching edges. Saving and loading the cross is
lossless (float32 EXR, zip compression).

Lat-long (equirectangular) maps follow :class:`LatLong`; its default is the convention
of the dev data and of Blender's world texture with +Z up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from torch import Tensor

from core.errors import SceneError
from core.render.envmap import EnvMap, sample_cube, texel_directions
from core.scene.imageio import read_image, write_image

# Block (row, column) of each face (storage order +X, -X, +Y, -Y, +Z, -Z) in the cross.
CROSS_BLOCKS: tuple[tuple[int, int], ...] = ((1, 2), (1, 0), (0, 1), (2, 1), (1, 1), (1, 3))

_LUMA = (0.2126, 0.7152, 0.0722)


@dataclass(frozen=True)
class LatLong:
    """A lat-long convention: where a world direction d lands in an H×W image.

    With e = ``rotation`` · d (world -> map frame; identity by default) and e normalised:
    u = 0.5 − atan2(e_y, e_x) / 2π (mod 1), θ = acos(e_z); in continuous pixel
    coordinates with pixel centres at integers, column = u·W − 0.5 (wrapping) and
    row = θ/π·(H − 1) for ``rows="endpoints"`` (the first and last rows sit on the poles;
    the dev data and Blender) or row = θ/π·H − 0.5 for ``rows="centers"`` (pixel rows
    tile [0, π]). So the middle column faces +X, the column at W/4 faces +Y, and the top
    row is +Z. For a Y-up map use ``rotation=((1, 0, 0), (0, 0, -1), (0, 1, 0))``
    (world +Y -> map +Z).
    """

    rotation: tuple[tuple[float, float, float], ...] | None = None
    rows: Literal["endpoints", "centers"] = "endpoints"

    def _rot(self, dtype: torch.dtype, device: torch.device) -> Tensor | None:
        if self.rotation is None:
            return None
        return torch.tensor(self.rotation, dtype=dtype, device=device)

    def to_pixel(self, dirs: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
        """Continuous (row, column) of directions (..., 3); columns not yet wrapped."""
        rot = self._rot(dirs.dtype, dirs.device)
        e = dirs if rot is None else dirs @ rot.T
        norm = e.norm(dim=-1).clamp_min(1e-30)
        u = torch.remainder(0.5 - torch.atan2(e[..., 1], e[..., 0]) / (2 * math.pi), 1.0)
        theta = torch.acos((e[..., 2] / norm).clamp(-1.0, 1.0))
        col = u * width - 0.5
        if self.rows == "endpoints":
            row = theta / math.pi * (height - 1)
        else:
            row = theta / math.pi * height - 0.5
        return row, col

    def pixel_directions(
        self,
        height: int,
        width: int,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str = "cpu",
    ) -> Tensor:
        """(H, W, 3) unit world directions of the pixel centres (inverse of ``to_pixel``)."""
        j = torch.arange(height, dtype=torch.float64)
        i = torch.arange(width, dtype=torch.float64)
        if self.rows == "endpoints":
            if height < 2:
                raise ValueError("an 'endpoints' lat-long map needs at least 2 rows")
            theta = j / (height - 1) * math.pi
        else:
            theta = (j + 0.5) / height * math.pi
        phi = (0.5 - (i + 0.5) / width) * 2 * math.pi
        tt, pp = torch.meshgrid(theta, phi, indexing="ij")
        e = torch.stack([tt.sin() * pp.cos(), tt.sin() * pp.sin(), tt.cos()], dim=-1)
        rot = self._rot(torch.float64, torch.device("cpu"))
        d = e if rot is None else e @ rot  # rot^-1 = rot^T; row form of rot^T e
        return d.to(dtype=dtype, device=device)


def sample_equirect(image: Tensor, dirs: Tensor, latlong: LatLong | None = None) -> Tensor:
    """Bilinear lookup of a lat-long image (H, W, C) at directions (..., 3) -> (..., C).

    Columns wrap around; rows are clamped at the poles.
    """
    latlong = latlong or LatLong()
    h, w, ch = image.shape
    lead = dirs.shape[:-1]
    row, col = latlong.to_pixel(dirs.reshape(-1, 3).to(image.dtype), h, w)
    c0 = col.floor()
    fc = (col - c0).unsqueeze(-1)
    c0 = c0.long()
    c1 = torch.remainder(c0 + 1, w)
    c0 = torch.remainder(c0, w)
    row = row.clamp(0.0, h - 1.0)
    r0 = row.floor().clamp(0, h - 1)
    fr = (row - r0).unsqueeze(-1)
    r0 = r0.long()
    r1 = (r0 + 1).clamp_max(h - 1)
    flat = image.reshape(-1, ch)
    top = flat[r0 * w + c0] * (1 - fc) + flat[r0 * w + c1] * fc
    bottom = flat[r1 * w + c0] * (1 - fc) + flat[r1 * w + c1] * fc
    return (top * (1 - fr) + bottom * fr).reshape(*lead, ch)


def equirect_to_cube(
    image: Tensor, resolution: int, latlong: LatLong | None = None, supersample: int = 1
) -> Tensor:
    """Resample a lat-long image (H, W, C) to cube texels (6, R, R, C).

    Each texel samples the image bilinearly at its centre direction; ``supersample`` > 1
    averages an s×s grid of directions inside the texel (a box filter, for downsizing).
    """
    r, s = resolution, max(1, int(supersample))
    if s == 1:
        return sample_equirect(image, texel_directions(r, image.dtype, image.device), latlong)
    fine = texel_directions(r * s, image.dtype, image.device)
    vals = sample_equirect(image, fine, latlong)
    return vals.view(6, r, s, r, s, -1).mean(dim=(2, 4))


def cube_to_equirect(
    texels: Tensor, height: int, width: int | None = None, latlong: LatLong | None = None
) -> Tensor:
    """Lat-long image (H, W, C) of cube texels (6, R, R, C); W defaults to 2H."""
    latlong = latlong or LatLong()
    width = width or 2 * height
    dirs = latlong.pixel_directions(height, width, texels.dtype, texels.device)
    return sample_cube(texels, dirs)


def cube_to_cross(texels: Tensor) -> Tensor:
    """Cube texels (6, R, R, C) -> horizontal cross (3R, 4R, C), unused blocks 0."""
    r, ch = texels.shape[1], texels.shape[-1]
    out = texels.new_zeros(3 * r, 4 * r, ch)
    for f, (br, bc) in enumerate(CROSS_BLOCKS):
        out[br * r : (br + 1) * r, bc * r : (bc + 1) * r] = texels[f]
    return out


def cross_to_cube(image: Tensor) -> Tensor:
    """Horizontal cross (3R, 4R, C) -> cube texels (6, R, R, C)."""
    h, w = image.shape[:2]
    if h % 3 or w != 4 * (h // 3):
        raise ValueError(f"a horizontal cube cross is 4R wide and 3R tall, got {w}x{h}")
    r = h // 3
    return torch.stack(
        [image[br * r : (br + 1) * r, bc * r : (bc + 1) * r] for br, bc in CROSS_BLOCKS]
    )


def _texels_of(envmap: EnvMap | Tensor) -> Tensor:
    t = envmap.texels() if isinstance(envmap, EnvMap) else envmap
    t = t.detach().float().cpu()
    if t.ndim != 4 or t.shape[0] != 6 or t.shape[1] != t.shape[2]:
        raise ValueError(f"cube texels must be (6, R, R, C), got {tuple(t.shape)}")
    if t.shape[-1] not in (1, 3):
        raise ValueError(f"only 1- or 3-channel maps can be saved, got {t.shape[-1]}")
    return t


def save_cube_cross(path: str | Path, envmap: EnvMap | Tensor) -> Path:
    """Write the map as a float32 EXR horizontal cube cross (lossless)."""
    return write_image(path, cube_to_cross(_texels_of(envmap)))


def save_equirect(
    path: str | Path,
    envmap: EnvMap | Tensor,
    height: int | None = None,
    latlong: LatLong | None = None,
    exposure: float = 1.0,
) -> Path:
    """Write a lat-long image (H = ``height`` or 2R, W = 2H) of the map.

    A float extension (.exr, .hdr) keeps linear values; an 8-bit one (.png, .jpg) is a
    preview: radiance × ``exposure``, sRGB-encoded, clipped to [0, 1].
    """
    t = _texels_of(envmap)
    img = cube_to_equirect(t, height or 2 * t.shape[1], latlong=latlong) * exposure
    return write_image(path, img)


def save_envmap(
    envmap: EnvMap | Tensor,
    directory: str | Path,
    stem: str = "envmap",
    latlong: LatLong | None = None,
    equirect_height: int | None = None,
    exposure: float = 1.0,
) -> dict[str, Path]:
    """Write ``{stem}_cross.exr``, ``{stem}_latlong.exr`` and ``{stem}_latlong.png``."""
    d = Path(directory)
    t = _texels_of(envmap)
    return {
        "cross": save_cube_cross(d / f"{stem}_cross.exr", t),
        "equirect": save_equirect(d / f"{stem}_latlong.exr", t, equirect_height, latlong),
        "preview": save_equirect(
            d / f"{stem}_latlong.png", t, equirect_height, latlong, exposure=exposure
        ),
    }


def load_envmap_texels(
    path: str | Path,
    resolution: int | None = None,
    layout: Literal["auto", "equirect", "cross"] = "auto",
    latlong: LatLong | None = None,
    scale: float = 1.0,
    channels: int = 3,
    supersample: int = 1,
) -> Tensor:
    """Read an EXR/HDR lat-long or cube-cross map as cube texels (6, R, R, C) float32.

    ``layout="auto"`` takes a 2:1 image as lat-long and a 4:3 one as a cross. R defaults
    to the cross's face size, or W/4 for a lat-long map. A cross at another resolution
    is resampled by seamless cube lookups at the new texel centres. Values are multiplied
    by ``scale`` (the dev data's ``meta.json:envmap.scale``). ``channels=1`` keeps
    Rec. 709 luminance.
    """
    rgb, _ = read_image(path)
    h, w = rgb.shape[:2]
    if layout == "auto":
        if w == 2 * h:
            layout = "equirect"
        elif 3 * w == 4 * h:
            layout = "cross"
        else:
            raise SceneError(
                f"cannot tell the env map layout of a {w}x{h} image: expected 2:1 "
                "(lat-long) or 4:3 (horizontal cube cross)",
                file=path,
            )
    if channels == 1:
        rgb = (rgb * torch.tensor(_LUMA)).sum(dim=-1, keepdim=True)
    elif channels != 3:
        raise ValueError(f"channels must be 1 or 3, got {channels}")
    if layout == "equirect":
        r = resolution or max(1, w // 4)
        cube = equirect_to_cube(rgb, r, latlong, supersample)
    elif layout == "cross":
        try:
            cube = cross_to_cube(rgb)
        except ValueError as exc:
            raise SceneError(str(exc), file=path) from exc
        if resolution is not None and resolution != cube.shape[1]:
            cube = sample_cube(cube, texel_directions(resolution, cube.dtype))
    else:
        raise ValueError(f"unknown layout {layout!r}")
    return (cube * scale).contiguous() if scale != 1.0 else cube.contiguous()


def init_envmap_from_file(
    envmap: EnvMap,
    path: str | Path,
    layout: Literal["auto", "equirect", "cross"] = "auto",
    latlong: LatLong | None = None,
    scale: float = 1.0,
    supersample: int = 1,
) -> EnvMap:
    """Set ``envmap``'s radiance from a file, resampled to its resolution; returns it."""
    cube = load_envmap_texels(
        path,
        envmap.resolution,
        layout,
        latlong,
        scale,
        channels=envmap.channels,
        supersample=supersample,
    )
    envmap.set_texels(cube)
    return envmap
