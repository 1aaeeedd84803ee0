"""The photos (and optional object masks) SfM starts from, checked before any work.

Every problem found here names the file: a folder with too few images, an image
that cannot be read, two images whose names differ only by extension (their views
and masks would be ambiguous), a missing mask or one of another size.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import OpenImageIO as oiio

from core.errors import SceneError
from core.scene.formats.common import list_images
from core.scene.sfm.errors import SfmError

MIN_IMAGES = 3  # two views fix no scale of a third; fewer cannot make a multi-view scene


@dataclass(frozen=True)
class InputImage:
    """One photo: ``name`` is its file name (what COLMAP records), ``size`` (width, height),
    ``camera`` what tells its camera apart (size, EXIF make, model and focal length)."""

    name: str
    path: Path
    size: tuple[int, int]
    camera: tuple = ()
    mask: Path | None = None


def collect_images(folder: str | Path, masks: str | Path | None = None) -> list[InputImage]:
    """The images of ``folder`` (sorted by name), each with its mask from ``masks``.

    A mask is the file in ``masks`` with the image's name or stem (``IMG_1.JPG`` →
    ``IMG_1.png``), white on the object, the size of its image. Masks are all or
    none: a capture with some views masked and others not would train inconsistently.
    """
    root = Path(folder)
    if not root.is_dir():
        raise SceneError("image folder not found (expected a folder of photos)", file=root)
    paths = list_images(root)
    if len(paths) < MIN_IMAGES:
        sub = [d.name for d in root.iterdir() if d.is_dir() and list_images(d)]
        hint = f"; images found in sub-folder(s) {', '.join(sorted(sub))}" if sub else ""
        raise SfmError(
            f"structure from motion needs at least {MIN_IMAGES} images of the object from "
            f"different viewpoints; {root} holds {len(paths)}{hint}"
        )
    seen: dict[str, Path] = {}
    for p in paths:
        if p.stem in seen:
            raise SceneError(
                f"two images share the name '{p.stem}' ({seen[p.stem].name} and {p.name}); "
                "rename one so each view has its own name",
                file=p,
            )
        seen[p.stem] = p
    mask_for = _pair_masks(paths, Path(masks)) if masks is not None else {}
    out = []
    for p in paths:
        size, exif = _header(p)
        m = mask_for.get(p)
        if m is not None and (ms := _header(m)[0]) != size:
            raise SceneError(
                f"mask is {ms[0]}x{ms[1]} but its image {p.name} is {size[0]}x{size[1]}", file=m
            )
        out.append(InputImage(p.name, p, size, (*size, *exif), m))
    return out


def _header(path: Path) -> tuple[tuple[int, int], tuple[str, str, str]]:
    """(width, height) and EXIF (make, model, focal length) from the header alone."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise SceneError(f"cannot read image: {oiio.geterror() or 'unknown format'}", file=path)
    try:
        spec = inp.spec()
        exif = tuple(str(spec.getattribute(k) or "") for k in ("Make", "Model", "Exif:FocalLength"))
        return (int(spec.width), int(spec.height)), exif
    finally:
        inp.close()


def _pair_masks(images: list[Path], folder: Path) -> dict[Path, Path]:
    if not folder.is_dir():
        raise SceneError("mask folder not found", file=folder)
    files = list_images(folder)
    by_name = {p.name: p for p in files}
    by_stem = {p.stem: p for p in files}
    out = {}
    for img in images:
        m = by_name.get(img.name) or by_stem.get(img.stem)
        if m is None:
            raise SceneError(
                f"no mask for image {img.name} (masks must cover every image, named like it: "
                f"{img.stem}.png or {img.name})",
                file=folder / f"{img.stem}.png",
            )
        out[img] = m
    return out
