"""Write the recovered model as a COLMAP scene Glint loads: undistorted pinhole images.

Glint's cameras are pinhole, so images are resampled through COLMAP's undistorter
(which also moves the sparse model's 2D observations); masks go through the same
warp. JPEG photos stay JPEG (quality 95), other formats keep theirs. With masks, 3D
points observed mostly on the background are dropped: the scene's bounds and the
initial Gaussians then come from the object, as they do for a masked capture with
given poses.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from core.scene.imageio import read_mask, write_image
from core.scene.sfm.colmap_lib import pycolmap
from core.scene.sfm.inputs import InputImage

JPEG_QUALITY = 95
OBJECT_FRACTION = 0.5  # a point is the object's when most of its observations are in masks


def drop_background_points(rec: Any, masks: Mapping[str, Path]) -> int:
    """Delete 3D points seen mostly outside the object masks; returns how many."""
    inside: dict[int, int] = {}
    seen: dict[int, int] = {}
    for im in rec.images.values():
        if not im.has_pose or im.name not in masks:
            continue
        m = read_mask(masks[im.name]).numpy()
        h, w = m.shape
        for p in im.points2D:
            if not p.has_point3D():
                continue
            x, y = int(np.floor(p.xy[0])), int(np.floor(p.xy[1]))
            pid = p.point3D_id
            seen[pid] = seen.get(pid, 0) + 1
            if 0 <= x < w and 0 <= y < h and m[y, x] > 0.5:
                inside[pid] = inside.get(pid, 0) + 1
    drop = [pid for pid, n in seen.items() if inside.get(pid, 0) < OBJECT_FRACTION * n]
    for pid in drop:
        rec.delete_point3D(pid)
    return len(drop)


def write_colmap_scene(
    rec: Any,
    staged: Mapping[str, InputImage],
    staged_dir: Path,
    out: Path,
    work_dir: Path,
    *,
    on_step: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """``out/images``, ``out/masks`` (when the inputs have masks) and ``out/sparse/0``.

    ``staged`` maps the names COLMAP used (plain, unique) to the user's images, whose
    own file names the scene keeps.
    """
    registered = sorted(im.name for im in rec.images.values() if im.has_pose)
    model_dir = work_dir / "model"
    model_dir.mkdir(parents=True, exist_ok=True)
    rec.write(model_dir)
    und = work_dir / "undistorted"
    pycolmap.undistort_images(
        und,
        model_dir,
        staged_dir,
        image_names=registered,
        output_type="COLMAP",
        jpeg_quality=JPEG_QUALITY,
    )
    final = pycolmap.Reconstruction(und / "sparse")
    (out / "images").mkdir(parents=True, exist_ok=True)
    ucam = pycolmap.UndistortCameraOptions()
    for k, im in enumerate(sorted(final.images.values(), key=lambda i: i.name)):
        src = staged[im.name]
        shutil.move(und / "images" / im.name, out / "images" / src.name)
        if src.mask is not None:
            bmp = pycolmap.Bitmap.read(src.mask, False)
            warped, _ = pycolmap.undistort_image(ucam, bmp, rec.cameras[im.camera_id])
            mask = warped.to_array().astype(np.float32) / 255.0
            write_image(out / "masks" / f"{Path(src.name).stem}.png", mask, encode_srgb=False)
        im.name = src.name
        if on_step:
            on_step(k + 1, len(registered))
    sparse = out / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    final.write(sparse)
    return {
        "cameras": [
            {
                "id": int(c.camera_id),
                "model": "PINHOLE",
                "width": int(c.width),
                "height": int(c.height),
                "params": [float(x) for x in c.params],
            }
            for c in final.cameras.values()
        ],
        "points3D": int(final.num_points3D()),
    }
