"""LLFF scenes: ``poses_bounds.npy`` + ``images/`` (+ ``images_<k>/``, ``masks/``).

Each row holds a 3x5 ``[R | t | hwf]`` camera-to-world whose rotation columns are
LLFF's camera axes (down, right, back), then near/far bounds. ``hwf`` describes the
*full-size* images, so the focal is scaled by (actual width / w), exactly LLFF's own
``factor`` logic for ``images_<k>`` folders; the principal point is the image centre.
Rows follow the sorted image names.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from core.errors import SceneError
from core.scene.cameras import Intrinsics
from core.scene.formats.common import (
    LoadOptions,
    ViewSpec,
    finish,
    image_size,
    invert_rigid,
    list_images,
    split_every,
    split_label,
    validate_rigid,
)
from core.scene.views import Scene

FILE = "poses_bounds.npy"


def read_poses_bounds(path: Path) -> np.ndarray:
    """The (N, 17) float64 array, or a SceneError naming what is wrong with it."""
    if not path.is_file():
        raise SceneError("file not found", file=path)
    with path.open("rb") as f:
        if f.read(6) != b"\x93NUMPY":
            raise SceneError("not a .npy file (bad header)", file=path)
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise SceneError(f"not a readable .npy array: {e}", file=path) from e
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise SceneError(f"expected shape (N, 17), got {arr.shape}", file=path)
    if not np.issubdtype(arr.dtype, np.number):
        raise SceneError(f"expected numbers, got dtype {arr.dtype}", file=path)
    return arr.astype(np.float64)


def llff_to_w2c(row: np.ndarray, *, file: Path, field: str) -> np.ndarray:
    """A row's [down, right, back] camera-to-world -> OpenCV world-to-camera 4x4."""
    P = row[:15].reshape(3, 5)
    c2w = np.eye(4)
    # OpenCV x = right = LLFF column 1, y = down = column 0, z = forward = -back
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = P[:, 1], P[:, 0], -P[:, 2]
    c2w[:3, 3] = P[:, 3]
    if not np.isfinite(row[:15]).all():
        raise SceneError("pose contains NaN or Inf", file=file, field=field)
    return invert_rigid(validate_rigid(c2w, file=file, field=field))


def _image_folder(root: Path, downscale: float) -> tuple[Path, float]:
    """``images_<k>`` when it matches the requested downscale, else ``images``.

    Returns the folder and the downscale still to apply after reading from it.
    """
    k = round(downscale)
    if k > 1 and abs(downscale - k) < 1e-9 and (root / f"images_{k}").is_dir():
        return root / f"images_{k}", 1.0
    if (root / "images").is_dir():
        return root / "images", downscale
    raise SceneError("image folder not found", file=root / "images")


def _masks(root: Path, images: list[Path]) -> list[Path | None]:
    """Masks with the same stem as each image in ``masks/``; all or none."""
    folder = root / "masks"
    if not folder.is_dir():
        return [None] * len(images)
    by_stem = {p.stem: p for p in list_images(folder)}
    by_name = {p.name: p for p in list_images(folder)}
    out: list[Path | None] = []
    for img in images:
        m = by_name.get(img.name) or by_stem.get(img.stem)
        if m is None:
            raise SceneError(
                f"no mask for image {img.name} (masks/ must cover every image)",
                file=folder / img.name,
            )
        out.append(m)
    return out


def load(root: Path, opts: LoadOptions) -> Scene:
    """Load an LLFF scene folder."""
    file = root / FILE
    arr = read_poses_bounds(file)
    folder, remaining = _image_folder(root, opts.downscale)
    images = list_images(folder)
    if not images:
        raise SceneError("no images in folder", file=folder)
    if len(images) != arr.shape[0]:
        raise SceneError(
            f"{arr.shape[0]} pose rows but {len(images)} images in {folder.name}/ "
            "(one row per image, in sorted name order)",
            file=file,
        )
    masks = _masks(root, images)
    width, height = image_size(images[0])
    specs = []
    for i, (img, row, mask) in enumerate(zip(images, arr, masks, strict=True)):
        field = f"row {i} ({img.name})"
        h, w, f = row[4], row[9], row[14]
        if not (np.isfinite([h, w, f]).all() and min(h, w, f) > 0):
            raise SceneError(f"hwf must be positive, got {[h, w, f]}", file=file, field=field)
        if abs(width / w - height / h) > 0.01 * width / w:
            raise SceneError(
                f"image aspect {width}x{height} does not match hwf {w:g}x{h:g}",
                file=file,
                field=field,
            )
        near, far = float(row[15]), float(row[16])
        if not (np.isfinite([near, far]).all() and 0 <= near <= far):
            raise SceneError(f"near/far bounds invalid: {near}, {far}", file=file, field=field)
        fs = f * width / w
        specs.append(
            ViewSpec(
                name=img.stem,
                image=img,
                world_to_cam=llff_to_w2c(row, file=file, field=field),
                intrinsics=Intrinsics(
                    float(fs), float(fs), width / 2.0, height / 2.0, width, height
                ),
                mask=mask,
                meta={"near": near, "far": far},
            )
        )
    meta: dict[str, Any] = {
        "warnings": [],
        "split": split_label(opts.test_every, "image by name"),
        "image_folder": folder.name,
    }
    train, test = split_every(specs, opts.test_every)
    return finish(train, test, "llff", root, opts, downscale=remaining, meta=meta)
