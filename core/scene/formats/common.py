"""Helpers every scene loader shares: validation, image loading, resizing, splits, bounds.

Loaders only parse their metadata into :class:`ViewSpec` records (image path, pose,
intrinsics at the file's resolution); everything after that (reading and checking
images, masks from alpha, area downscaling, the train/test split, ``max_views``,
scene bounds) happens here once, so every format behaves the same.
"""

from __future__ import annotations

import json
import math
import posixpath
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
import torch
import torch.nn.functional as F
from torch import Tensor

from core.errors import SceneError
from core.scene.cameras import Camera, Intrinsics
from core.scene.exposure import exposure_warning
from core.scene.imageio import read_image, read_mask
from core.scene.views import Scene, View, bounds_from_cameras

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".hdr")
ROTATION_TOL = 1e-3  # float32 poses are good to ~1e-7; anything past this is not a rotation


@dataclass
class ViewSpec:
    """One view as a loader parsed it, before any pixel is read.

    ``intrinsics`` describe the image file as stored (its width/height are checked
    against the decoded image). ``mask`` is a separate mask file; without one the
    image's alpha channel (if any) becomes the mask.
    """

    name: str
    image: Path
    world_to_cam: np.ndarray
    intrinsics: Intrinsics
    mask: Path | None = None
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass
class LoadOptions:
    """The caller's choices, passed from ``load_scene`` to each format's loader."""

    downscale: float = 1.0
    test_every: int = 8
    linearize: bool = True
    max_views: int | None = None
    allow_outside_root: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.downscale) and self.downscale >= 1.0):
            raise ValueError(f"downscale must be a finite number >= 1, got {self.downscale}")
        if self.test_every < 0 or self.test_every == 1:
            raise ValueError("test_every must be 0 (no test views) or >= 2")
        if self.max_views is not None and self.max_views < 1:
            raise ValueError("max_views must be >= 1 or None")


# -- metadata parsing ------------------------------------------------------------


def load_json(path: Path) -> Any:
    """Parse a JSON file; errors name the file and the line/column at fault."""
    if not path.is_file():
        raise SceneError("file not found", file=path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"cannot read file: {e}", file=path) from e
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise SceneError(
            f"malformed JSON at line {e.lineno}, column {e.colno}: {e.msg}", file=path
        ) from e


def require(obj: Any, key: str, *, file: Path, field: str) -> Any:
    """``obj[key]``, or a SceneError naming the file and the full field path."""
    if not isinstance(obj, dict):
        parent = field.rsplit(".", 1)[0] if "." in field else "(top level)"
        raise SceneError(f"expected an object at '{parent}'", file=file, field=field)
    if key not in obj:
        raise SceneError("missing required key", file=file, field=field)
    return obj[key]


def as_float(value: Any, *, file: Path, field: str, positive: bool = False) -> float:
    """A finite (optionally positive) number, or a SceneError naming the field."""
    try:
        x = float(value)
    except (TypeError, ValueError, OverflowError):
        raise SceneError(f"expected a number, got {value!r}", file=file, field=field) from None
    if not math.isfinite(x) or (positive and x <= 0):
        raise SceneError(
            f"expected a finite{' positive' if positive else ''} number, got {x}",
            file=file,
            field=field,
        )
    return x


def as_matrix(value: Any, shape: tuple[int, ...], *, file: Path, field: str) -> np.ndarray:
    """A float64 array of the given shape (finite), or a SceneError naming the field."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise SceneError(
            f"expected a {'x'.join(map(str, shape))} matrix of numbers", file=file, field=field
        ) from None
    if arr.shape != shape:
        raise SceneError(
            f"expected a {'x'.join(map(str, shape))} matrix, got shape {arr.shape}",
            file=file,
            field=field,
        )
    if not np.isfinite(arr).all():
        raise SceneError("matrix contains NaN or Inf", file=file, field=field)
    return arr


def parse_pose(value: Any, *, file: Path, field: str) -> np.ndarray:
    """A JSON/array 3x4 or 4x4 rigid pose -> validated 4x4 float64."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise SceneError(
            "expected a 4x4 (or 3x4) matrix of numbers", file=file, field=field
        ) from None
    return validate_rigid(arr, file=file, field=field)


def validate_rigid(
    M: np.ndarray, *, file: Path, field: str, tol: float = ROTATION_TOL
) -> np.ndarray:
    """Check a 3x4/4x4 rigid transform and return it as 4x4 float64 with an exact rotation.

    Rejects NaN/Inf, a bottom row other than (0, 0, 0, 1), and a rotation block that
    is not orthonormal with det +1 within ``tol`` (a scaled, sheared or mirrored
    pose would silently corrupt every downstream projection). Rotations within the
    tolerance are snapped to the nearest rotation so ``R.T`` is the exact inverse.
    """
    M = np.asarray(M, dtype=np.float64)
    if M.shape not in ((3, 4), (4, 4)):
        raise SceneError(
            f"expected a 3x4 or 4x4 matrix, got shape {M.shape}", file=file, field=field
        )
    if not np.isfinite(M).all():
        raise SceneError("pose contains NaN or Inf", file=file, field=field)
    if M.shape == (4, 4) and np.abs(M[3] - [0.0, 0.0, 0.0, 1.0]).max() > tol:
        raise SceneError(
            f"bottom row must be (0, 0, 0, 1), got {M[3].tolist()}", file=file, field=field
        )
    R = M[:3, :3]
    ortho = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if det < 0:
        raise SceneError(
            f"rotation is a reflection (det = {det:.6g}): the pose flips handedness",
            file=file,
            field=field,
        )
    if ortho > tol or abs(det - 1.0) > 3 * tol:
        raise SceneError(
            f"rotation is not rigid (max |RᵀR − I| = {ortho:.3g}, det = {det:.6g}; "
            "expected an orthonormal matrix with det +1)",
            file=file,
            field=field,
        )
    out = np.eye(4)
    out[:3, :4] = M[:3, :4]
    if ortho > 1e-12:
        U, _, Vt = np.linalg.svd(R)
        out[:3, :3] = U @ Vt
    return out


def opengl_c2w_to_w2c(c2w: np.ndarray) -> np.ndarray:
    """OpenGL/Blender camera-to-world (validated 4x4) -> OpenCV world-to-camera 4x4.

    Same as ``Camera.from_opengl_c2w`` but with an exact rigid inverse.
    """
    c2w_cv = np.array(c2w, dtype=np.float64)
    c2w_cv[:3, 1:3] *= -1.0  # y up -> y down, z back -> z forward
    return invert_rigid(c2w_cv)


def w2c_to_opengl_c2w(w2c: np.ndarray) -> np.ndarray:
    """Inverse of :func:`opengl_c2w_to_w2c` (used by the writers)."""
    c2w = invert_rigid(np.asarray(w2c, dtype=np.float64))
    c2w[:3, 1:3] *= -1.0
    return c2w


def invert_rigid(M: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 (exact transpose of the rotation, no general inversion)."""
    out = np.eye(4)
    out[:3, :3] = M[:3, :3].T
    out[:3, 3] = -M[:3, :3].T @ M[:3, 3]
    return out


# -- files -------------------------------------------------------------------------


def check_inside(rel: str, *, file: Path, field: str) -> None:
    """Refuse a path that leaves the scene folder (absolute, or climbing with ``..``).

    Scene files come from users of a service: a ``file_path`` of ``/etc/...`` or
    ``../../other_scene/x.png`` must not read files outside the upload. Checked on
    the text of the path, so symlinks inside the scene folder keep working.
    """
    norm = posixpath.normpath(rel.replace("\\", "/"))
    if norm.startswith("/") or norm == ".." or norm.startswith("../") or ":" in norm.split("/")[0]:
        raise SceneError(
            f"path '{rel}' leaves the scene folder "
            "(pass allow_outside_root=True to load_scene to allow it)",
            file=file,
            field=field,
        )


def find_image(base: Path, rel: str, *, file: Path, field: str, confine: bool = True) -> Path:
    """Resolve an image path that may lack its extension (NeRF-synthetic ``./train/r_0``)."""
    if confine:
        check_inside(rel, file=file, field=field)
    p = (base / rel).resolve() if not Path(rel).is_absolute() else Path(rel)
    if p.is_file():
        return p
    for ext in IMAGE_EXTS:
        for e in (ext, ext.upper()):
            q = p.with_name(p.name + e)
            if q.is_file():
                return q
    raise SceneError(
        f"image '{rel}' not found (looked for {p} and {p.name}.{{png,jpg,exr,...}})",
        file=file,
        field=field,
    )


def list_images(folder: Path) -> list[Path]:
    """Image files in ``folder`` sorted by name (hidden files skipped)."""
    return sorted(
        p
        for p in folder.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_EXTS
    )


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header alone, without decoding pixels."""
    if not path.is_file():
        raise SceneError("image file not found", file=path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise SceneError(f"cannot read image: {oiio.geterror() or 'unknown format'}", file=path)
    try:
        spec = inp.spec()
        return int(spec.width), int(spec.height)
    finally:
        inp.close()


# -- pixels ------------------------------------------------------------------------


def area_resize(x: Tensor, height: int, width: int) -> Tensor:
    """Area (box) filter an (H, W, C) or (H, W) image to the given size."""
    if x.shape[0] == height and x.shape[1] == width:
        return x
    chw = x[None, None] if x.ndim == 2 else x.permute(2, 0, 1)[None]
    out = F.interpolate(chw, size=(height, width), mode="area")[0]
    return out[0] if x.ndim == 2 else out.permute(1, 2, 0).contiguous()


def downscale_rgba(
    rgb: Tensor, alpha: Tensor | None, height: int, width: int
) -> tuple[Tensor, Tensor | None]:
    """Area-downscale straight-alpha RGBA correctly: average premultiplied colour.

    Averaging straight RGB would bleed the (meaningless) colour of transparent
    pixels into the object's edge; premultiplying first weights each sample by its
    coverage, and dividing back keeps the result straight alpha.
    """
    if alpha is None:
        return area_resize(rgb, height, width), None
    a = area_resize(alpha, height, width)
    pre = area_resize(rgb * alpha[..., None], height, width)
    plain = area_resize(rgb, height, width)
    # pre / a is a coverage-weighted mean of the source colours, so it stays in their range
    out = torch.where(a[..., None] > 1e-6, pre / a.clamp_min(1e-6)[..., None], plain)
    return out, a


def _load_one(spec: ViewSpec, opts: LoadOptions, scale: float) -> View:
    rgb, alpha = read_image(spec.image, linearize=opts.linearize)
    h, w = int(rgb.shape[0]), int(rgb.shape[1])
    intr = spec.intrinsics
    if (w, h) != (intr.width, intr.height):
        raise SceneError(
            f"image is {w}x{h} but its camera expects {intr.width}x{intr.height} "
            "(every image must match its camera; images of one camera must share a size)",
            file=spec.image,
        )
    # clamp keeps NaN: a non-finite alpha or mask would make every training target NaN
    if alpha is not None and not bool(torch.isfinite(alpha).all()):
        raise SceneError("alpha channel contains NaN or Inf values", file=spec.image)
    mask = alpha.clamp(0.0, 1.0) if alpha is not None else None
    if spec.mask is not None:
        mask = read_mask(spec.mask)
        if not bool(torch.isfinite(mask).all()):
            raise SceneError("mask contains NaN or Inf values", file=spec.mask)
        mh, mw = mask.shape
        if (mw, mh) != (w, h):
            if abs(mw * h - mh * w) > max(mw, w):  # different aspect: not the same picture
                raise SceneError(f"mask is {mw}x{mh} but its image is {w}x{h}", file=spec.mask)
            mask = area_resize(mask, h, w)
    cam = Camera(intr, torch.from_numpy(spec.world_to_cam.copy()), spec.name, dict(spec.meta))
    if scale != 1.0:
        cam = cam.scaled(scale)
        if spec.mask is None:
            rgb, mask = downscale_rgba(rgb, mask, cam.height, cam.width)
        else:  # a separate mask does not describe RGB coverage: filter independently
            rgb = area_resize(rgb, cam.height, cam.width)
            mask = area_resize(mask, cam.height, cam.width)
    return View(camera=cam, image=rgb.contiguous(), mask=mask, name=spec.name, path=spec.image)


def load_views(
    specs: Sequence[ViewSpec], opts: LoadOptions, downscale: float | None = None
) -> list[View]:
    """Read, check and downscale the images of ``specs`` (threads: decoding drops the GIL)."""
    d = opts.downscale if downscale is None else downscale
    scale = 1.0 / d
    if len(specs) <= 2:
        return [_load_one(s, opts, scale) for s in specs]
    with ThreadPoolExecutor(max_workers=4) as pool:
        return list(pool.map(lambda s: _load_one(s, opts, scale), specs))


# -- splits and bounds ---------------------------------------------------------------


def split_every(items: Sequence[Any], test_every: int) -> tuple[list[Any], list[Any]]:
    """LLFF convention: items 0, k, 2k, ... are test views; a single item is train only."""
    if test_every <= 0 or len(items) < 2:
        return list(items), []
    train = [x for i, x in enumerate(items) if i % test_every != 0]
    test = [x for i, x in enumerate(items) if i % test_every == 0]
    return train, test


def split_label(test_every: int, unit: str) -> str:
    """How a split-less format was split, for ``Scene.meta['split']``."""
    return f"every {test_every}th {unit} is a test view" if test_every > 0 else "all views train"


def evenly(items: Sequence[Any], k: int) -> list[Any]:
    """``k`` items spread evenly over ``items`` (first and last included), order kept."""
    if k >= len(items):
        return list(items)
    if k <= 0:
        return []
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, k)).astype(int))
    return [items[i] for i in idx]


def cap_views(
    train: Sequence[Any], test: Sequence[Any], max_views: int | None
) -> tuple[list[Any], list[Any]]:
    """Keep at most ``max_views`` in all, shared between the splits in proportion.

    Applied before any image is read, so a capped load of a large scene is fast; the
    test views kept are a subset of the full test split, never train views.
    """
    if max_views is None or len(train) + len(test) <= max_views:
        return list(train), list(test)
    total = len(train) + len(test)
    n_test = round(max_views * len(test) / total)
    if test and max_views >= 2:
        n_test = max(1, n_test)
    n_test = min(n_test, max_views - 1) if train else max_views
    return evenly(train, max_views - n_test), evenly(test, n_test)


def points_bounds(points: Tensor) -> tuple[Tensor, float]:
    """Robust centre/radius of a sparse cloud: ignores the few far outliers SfM leaves."""
    p = points.to(torch.float64)
    lo = torch.quantile(p, 0.02, dim=0)
    hi = torch.quantile(p, 0.98, dim=0)
    center = 0.5 * (lo + hi)
    dist = (p - center).norm(dim=-1)
    radius = float(torch.quantile(dist, 0.95))
    return center, radius if radius > 0 else 1.0


def build_scene(
    train: list[View],
    test: list[View],
    fmt: str,
    root: Path,
    *,
    points: Tensor | None = None,
    point_colors: Tensor | None = None,
    meta: dict[str, Any] | None = None,
) -> Scene:
    """Assemble a Scene; bounds from the point cloud when there is one, else from cameras."""
    if not train and not test:
        raise SceneError("the scene has no views", file=root)
    meta = dict(meta or {})
    if points is not None and points.shape[0] >= 8:
        center, radius = points_bounds(points)
        meta.setdefault("bounds_from", "points")
    else:
        center, radius = bounds_from_cameras([v.camera for v in train + test])
        meta.setdefault("bounds_from", "cameras")
    meta.setdefault("warnings", [])
    return Scene(
        train=train,
        test=test,
        center=center,
        radius=radius,
        format=fmt,
        root=root,
        points=points,
        point_colors=point_colors,
        meta=meta,
    )


def finish(
    specs_train: Sequence[ViewSpec],
    specs_test: Sequence[ViewSpec],
    fmt: str,
    root: Path,
    opts: LoadOptions,
    *,
    downscale: float | None = None,
    points: Tensor | None = None,
    point_colors: Tensor | None = None,
    meta: dict[str, Any] | None = None,
) -> Scene:
    """Cap, read and assemble: the common tail of every loader."""
    if not specs_train and not specs_test:
        raise SceneError("the scene has no views", file=root)
    tr, te = cap_views(specs_train, specs_test, opts.max_views)
    views = load_views(tr + te, opts, downscale)
    if warning := exposure_warning([s.image for s in tr + te]):
        meta = {**(meta or {}), "warnings": [*(meta or {}).get("warnings", []), warning]}
    return build_scene(
        views[: len(tr)],
        views[len(tr) :],
        fmt,
        root,
        points=points,
        point_colors=point_colors,
        meta=meta,
    )
