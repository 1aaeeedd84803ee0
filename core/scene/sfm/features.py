"""SIFT features into a COLMAP database, a few images at a time so progress can be shown.

Images that share size and EXIF camera (make, model, focal length) share one
camera: one set of intrinsics estimated from all of them, which is what a photo
series from one camera at one zoom has, and far better constrained than one camera
per image (goldcape: one focal of 842.5–843.2 px against the LLFF 843.1, where one
camera per photo scatters them over 829–865 px). Feature masks, when asked for,
keep keypoints off the object: COLMAP drops keypoints where a mask image is black.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from core.scene.imageio import read_mask, write_image
from core.scene.sfm.colmap_lib import pycolmap
from core.scene.sfm.errors import SfmError
from core.scene.sfm.inputs import InputImage

# COLMAP's long-standing cap: larger photos are downsampled for extraction only
# (keypoints are scaled back), bounding time and memory for 12+ MP phone images.
MAX_IMAGE_SIZE = 3200
MAX_FEATURES = 8192


def camera_groups(images: Sequence[InputImage]) -> list[list[InputImage]]:
    """Images grouped by camera (size + EXIF), in order of first appearance."""
    groups: dict[tuple, list[InputImage]] = {}
    for im in images:
        groups.setdefault(im.camera, []).append(im)
    return list(groups.values())


def write_feature_masks(images: Sequence[InputImage], folder: Path) -> Path:
    """COLMAP feature masks (``<image name>.png``, black = no keypoints) that cover the
    object of each image's mask, so keypoints come from the background only."""
    folder.mkdir(parents=True, exist_ok=True)
    for im in images:
        if im.mask is None:
            raise ValueError(f"{im.name} has no mask")
        keep = (read_mask(im.mask).numpy() < 0.5).astype(np.float32)
        write_image(folder / f"{im.name}.png", keep, encode_srgb=False)
    return folder


def extract(
    database: Path,
    image_dir: Path,
    images: Sequence[InputImage],
    *,
    feature_mask_dir: Path | None = None,
    on_step: Callable[[int, int], None] | None = None,
    chunk: int | None = None,
) -> None:
    """Import every image (one camera per group), then extract SIFT ``chunk`` images
    at a time (default: about 8 calls; each call has a start-up cost), reporting
    ``on_step(done, total)``."""
    names = [im.name for im in images]
    reader = pycolmap.ImageReaderOptions()
    if feature_mask_dir is not None:
        reader.mask_path = str(feature_mask_dir)
    opts = pycolmap.FeatureExtractionOptions()
    opts.max_image_size = MAX_IMAGE_SIZE
    opts.sift.max_num_features = MAX_FEATURES
    pycolmap.Database.open(database).close()
    for group in camera_groups(images):
        pycolmap.import_images(
            database, image_dir, pycolmap.CameraMode.SINGLE, [im.name for im in group], reader
        )
    step = chunk or max(16, -(-len(names) // 8))
    for s in range(0, len(names), step):
        pycolmap.extract_features(
            database,
            image_dir,
            names[s : s + step],
            reader_options=reader,
            extraction_options=opts,
            device=pycolmap.Device.cpu,
        )
        if on_step:
            on_step(min(s + step, len(names)), len(names))
    _check_extracted(database, images)


def _check_extracted(database: Path, images: Sequence[InputImage]) -> None:
    """Every image must be in the database with keypoints; COLMAP skips unreadable ones."""
    db = pycolmap.Database.open(database)
    try:
        stored = {im.name: im.image_id for im in db.read_all_images()}
        missing = [im for im in images if im.name not in stored]
        if missing:
            raise SfmError(
                f"could not read {len(missing)} image(s) for feature extraction: "
                + ", ".join(str(im.path) for im in missing)
                + " (corrupt file or unsupported encoding?)",
                unregistered=[im.name for im in missing],
            )
        counts = {im.name: db.num_keypoints_for_image(stored[im.name]) for im in images}
    finally:
        db.close()
    if sum(counts.values()) == 0:
        raise SfmError(
            "no features found in any image: the photos are blank, too dark or too blurred "
            "(or a feature mask covers everything)"
        )


def descriptors(database: Path, names: Sequence[str]) -> list[np.ndarray]:
    """SIFT descriptors (uint8, (n_i, 128)) of each image, in the order of ``names``."""
    db = pycolmap.Database.open(database)
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        return [np.asarray(db.read_descriptors(ids[n]).data) for n in names]
    finally:
        db.close()


def keypoint_counts(database: Path) -> dict[str, int]:
    """Keypoints per image name (for the report)."""
    db = pycolmap.Database.open(database)
    try:
        return {im.name: db.num_keypoints_for_image(im.image_id) for im in db.read_all_images()}
    finally:
        db.close()
