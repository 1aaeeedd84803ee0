"""Image files in and out through OpenImageIO (PNG, JPEG, EXR, HDR, 8/16-bit, float).

Files hold display-encoded (sRGB) values for 8/16-bit formats and linear values
for float formats; in memory Glint always works in linear light.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import torch
from torch import Tensor

from core.errors import SceneError

_FLOAT_EXTS = {".exr", ".hdr", ".pfm", ".tif", ".tiff"}


def srgb_to_linear(x: Tensor | np.ndarray) -> Tensor | np.ndarray:
    """IEC 61966-2-1 decoding (exact piecewise form, not a 2.2 power)."""
    if isinstance(x, np.ndarray):
        return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4)
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp_min(0.04045) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: Tensor | np.ndarray) -> Tensor | np.ndarray:
    """IEC 61966-2-1 encoding; negative inputs map to 0."""
    if isinstance(x, np.ndarray):
        x = np.maximum(x, 0.0)
        return np.where(
            x <= 0.0031308, x * 12.92, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055
        )
    x = x.clamp_min(0.0)
    return torch.where(
        x <= 0.0031308, x * 12.92, 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055
    )


def read_image_array(path: str | Path) -> tuple[np.ndarray, bool]:
    """Read a file into float32 (H, W, C) as stored; returns (pixels, is_float_format).

    Raises SceneError naming the file when it is missing or cannot be decoded.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError("image file not found", file=path)
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # files store straight alpha
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise SceneError(f"cannot read image: {oiio.geterror() or 'unknown format'}", file=path)
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        err = inp.geterror()
    finally:
        inp.close()
    if pixels is None or (isinstance(pixels, np.ndarray) and pixels.size == 0):
        raise SceneError(f"cannot decode image: {err or 'no pixel data'}", file=path)
    arr = np.asarray(pixels, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    is_float = spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE)
    return arr, is_float


def read_image(path: str | Path, linearize: bool = True) -> tuple[Tensor, Tensor | None]:
    """Read RGB(A) as linear float32 (H, W, 3) and alpha (H, W) or None.

    Gray images are expanded to RGB. 8/16-bit files are decoded from sRGB when
    ``linearize`` is true; float files are taken as linear already.
    """
    arr, is_float = read_image_array(path)
    c = arr.shape[2]
    if c == 1:
        rgb, alpha = np.repeat(arr, 3, axis=2), None
    elif c == 2:
        rgb, alpha = np.repeat(arr[..., :1], 3, axis=2), arr[..., 1]
    else:
        rgb = arr[..., :3]
        alpha = arr[..., 3] if c >= 4 else None
    if not np.isfinite(rgb).all():
        raise SceneError("image contains NaN or Inf values", file=path)
    if linearize and not is_float:
        rgb = srgb_to_linear(rgb)
    rgb_t = torch.from_numpy(np.ascontiguousarray(rgb, dtype=np.float32))
    alpha_t = None if alpha is None else torch.from_numpy(np.ascontiguousarray(alpha, np.float32))
    return rgb_t, alpha_t


def read_mask(path: str | Path) -> Tensor:
    """Read a mask file as (H, W) float32 in [0, 1] (first channel; white = object)."""
    arr, _ = read_image_array(path)
    if arr.shape[2] in (2, 4):
        m = arr[..., -1] if arr.shape[2] == 2 else arr[..., 3]
        if float(m.min()) == float(m.max()):  # opaque alpha: use luminance instead
            m = arr[..., 0]
    else:
        m = arr[..., 0]
    return torch.from_numpy(np.clip(np.ascontiguousarray(m, np.float32), 0.0, 1.0))


def write_image(
    path: str | Path,
    image: Tensor | np.ndarray,
    alpha: Tensor | np.ndarray | None = None,
    encode_srgb: bool = True,
    bits: int = 8,
) -> Path:
    """Write linear float (H, W, C) to disk; format from the extension.

    8/16-bit formats are sRGB-encoded (when ``encode_srgb``) and clipped to [0, 1];
    float formats (EXR, HDR) keep linear values as float32 (EXR: half if bits=16).
    The file is written to a temporary name and renamed, so readers never see half a file.
    """
    path = Path(path)
    arr = image.detach().cpu().numpy() if isinstance(image, Tensor) else np.asarray(image)
    arr = arr.astype(np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    is_float = path.suffix.lower() in _FLOAT_EXTS
    if not is_float:
        if encode_srgb:
            arr = linear_to_srgb(arr)
        arr = np.clip(arr, 0.0, 1.0)
    if alpha is not None:
        a = alpha.detach().cpu().numpy() if isinstance(alpha, Tensor) else np.asarray(alpha)
        arr = np.concatenate([arr, np.clip(a.astype(np.float32), 0, 1)[..., None]], axis=2)
    h, w, c = arr.shape
    if is_float:
        fmt = oiio.HALF if bits == 16 else oiio.FLOAT
    else:
        fmt = oiio.UINT16 if bits == 16 else oiio.UINT8
    spec = oiio.ImageSpec(w, h, c, fmt)
    if path.suffix.lower() == ".exr":
        spec.attribute("compression", "zip")
    if c == 4:
        spec.alpha_channel = 3
        spec.attribute("oiio:UnassociatedAlpha", 1)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    out = oiio.ImageOutput.create(str(tmp))
    if out is None:
        raise OSError(f"{path}: no image writer for this extension ({oiio.geterror()})")
    try:
        if not out.open(str(tmp), spec):
            raise OSError(f"{path}: cannot open for writing ({out.geterror()})")
        if not out.write_image(np.ascontiguousarray(arr)):
            raise OSError(f"{path}: write failed ({out.geterror()})")
    finally:
        out.close()
    tmp.replace(path)
    return path
