"""Images-only uploads: plain photos (and optional masks) without poses.

Users bring photographs, not camera files. An upload in none of the scene formats whose
photos sit at the top level or in ``images/`` (with masks, if any, in ``masks/``, named
like the photos) is a valid scene of format ``images``: it is committed after the photos
(and masks) were checked, and every training job on it starts with an ``sfm`` phase
(:mod:`api.service.sfm_phase`) that recovers the cameras. One wrapping folder (what
zipping a folder leaves) is looked through when nothing else is beside it.

Torch, OpenImageIO and pycolmap are imported only when a scene is examined, so the
service layer starts without them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

PHOTOS_FORMAT = "images"  # Scene.format of an images-only scene
MASKS_FOLDER = "masks"


@dataclass(frozen=True)
class PhotoFolders:
    """Where the photos of an images-only scene are: a flat folder, and its masks."""

    images: Path
    masks: Path | None


def _has_format(root: Path) -> bool:
    from core.errors import SceneError
    from core.scene.formats import detect_format

    try:
        detect_format(root)
    except SceneError:
        return False
    return True


def _photos_in(root: Path) -> PhotoFolders | None:
    from core.scene.formats.common import list_images

    masks = root / MASKS_FOLDER
    mask_dir = masks if masks.is_dir() else None
    if list_images(root):
        return PhotoFolders(root, mask_dir)
    sub = root / "images"
    if sub.is_dir() and list_images(sub):
        return PhotoFolders(sub, mask_dir)
    return None


def find_photos(root: Path) -> PhotoFolders | None:
    """The photo and mask folders of an images-only scene, or None when ``root`` is in a
    scene format (it has poses) or holds no photos where they are looked for."""
    if not root.is_dir() or _has_format(root):
        return None
    found = _photos_in(root)
    if found is None:
        entries = [p for p in root.iterdir() if not p.name.startswith((".", "__"))]
        if len(entries) == 1 and entries[0].is_dir():  # a wrapping folder, nothing beside it
            found = _photos_in(entries[0])
    return found


def photos_report(folders: PhotoFolders) -> dict[str, Any]:
    """The validation report of an images-only scene (the shape of a posed scene's, with
    ``needs_sfm``): every photo's header and every mask checked, as SfM will need them.

    Raises :class:`core.errors.SceneError` (a file named) or
    :class:`core.scene.sfm.SfmError` (too few photos). Cameras, centre and radius are
    unknown until SfM (null); the split is the one a COLMAP scene of these photos gets
    when every photo registers (every 8th a test view).
    """
    from core.scene.exposure import exposure_warning
    from core.scene.formats.common import split_every
    from core.scene.sfm.inputs import collect_images

    photos = collect_images(folders.images, folders.masks)
    train, test = split_every(photos, 8)
    sizes = sorted({p.size for p in photos})
    warning = exposure_warning([p.path for p in photos])
    return {
        "format": PHOTOS_FORMAT,
        "needs_sfm": True,
        "views": len(photos),
        "train_views": len(train),
        "test_views": len(test),
        "resolution": list(photos[0].size),
        "resolutions": [list(s) for s in sizes],
        "intrinsics": None,
        "masks": folders.masks is not None,
        "points": 0,
        "center": None,
        "radius": None,
        "warnings": [warning] if warning else [],
    }
