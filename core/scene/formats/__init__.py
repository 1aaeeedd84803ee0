"""Scene formats in, one :class:`~core.scene.views.Scene` out.

``load_scene(path)`` detects the format from the files present (Blender/NeRF-synthetic,
nerfstudio/Instant-NGP, COLMAP, LLFF, NeRO), converts cameras to Glint's OpenCV
world-to-camera convention, reads images as linear float with masks from alpha or
mask files, and raises :class:`~core.errors.SceneError` naming the file and field
for anything malformed. Writers for every format live in :mod:`core.scene.formats.writers`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from core.errors import SceneError
from core.scene.formats import blender, colmap, llff, nerfstudio, nero
from core.scene.formats.common import LoadOptions
from core.scene.views import Scene

FORMATS = ("blender", "nerfstudio", "colmap", "llff", "nero")
_LOADERS: dict[str, Callable[[Path, LoadOptions], Scene]] = {
    "blender": blender.load,
    "nerfstudio": nerfstudio.load,
    "colmap": colmap.load,
    "llff": llff.load,
    "nero": nero.load,
}
# what each format is recognised by, in priority order (COLMAP before LLFF: LLFF
# folders made by imgs2poses often keep the COLMAP model they came from)
_MARKERS = (
    ("blender", "transforms_train.json"),
    ("nerfstudio", "transforms.json"),
    ("colmap", "sparse/0/cameras.{bin,txt} or sparse/cameras.{bin,txt}"),
    ("llff", "poses_bounds.npy"),
    ("nero", "*-camera.pkl"),
)
_FILE_FORMATS = {
    "transforms_train.json": "blender",
    "transforms.json": "nerfstudio",
    "poses_bounds.npy": "llff",
}


def _formats_in(root: Path) -> list[str]:
    found = []
    if (root / "transforms_train.json").is_file():
        found.append("blender")
    if (root / "transforms.json").is_file():
        found.append("nerfstudio")
    if colmap.find_sparse_dir(root) is not None:
        found.append("colmap")
    if (root / "poses_bounds.npy").is_file():
        found.append("llff")
    if nero.find_keys(root):
        found.append("nero")
    return found


def _resolve(path: str | Path) -> tuple[Path, list[str]]:
    """Scene root and the formats found there (best first).

    Accepts the scene folder, a marker file inside it (``transforms.json``, ...), or
    a folder whose only sub-folder is the scene (what unpacking an archive leaves).
    """
    p = Path(path)
    if not p.exists():
        raise SceneError("scene path does not exist", file=p)
    if p.is_file():
        fmt = _FILE_FORMATS.get(p.name)
        if fmt is None:
            raise SceneError("not a scene folder or a known scene file", file=p)
        return p.parent, [fmt]
    found = _formats_in(p)
    if not found:
        subdirs = [d for d in p.iterdir() if d.is_dir() and not d.name.startswith((".", "__"))]
        if len(subdirs) == 1 and (inner := _formats_in(subdirs[0])):
            return subdirs[0], inner
        looked = "; ".join(f"{m} ({f})" for f, m in _MARKERS)
        raise SceneError(f"no known scene format found; looked for {looked}", file=p)
    return p, found


def detect_format(path: str | Path) -> str:
    """Name of the scene format at ``path``: one of :data:`FORMATS`."""
    return _resolve(path)[1][0]


def load_scene(
    path: str | Path,
    *,
    downscale: float = 1.0,
    test_every: int = 8,
    linearize: bool = True,
    max_views: int | None = None,
    format: str | None = None,
    allow_outside_root: bool = False,
) -> Scene:
    """Load a scene folder in any supported format.

    Args:
        path: the scene folder (or its ``transforms*.json`` / ``poses_bounds.npy``).
        downscale: divide the image size by this (>= 1), area-filtered; intrinsics follow.
        test_every: where the format has no split, every ``test_every``-th view is a test
            view (LLFF convention; 0 = no test views).
        linearize: decode 8/16-bit images from sRGB to linear light.
        max_views: read at most this many views in all (spread evenly over each split),
            to keep previews and tests fast.
        format: force a format instead of detecting it (when a folder holds two).
        allow_outside_root: let metadata name image files outside the scene folder
            (absolute or ``../`` paths); off by default because scenes may be uploads.
    """
    opts = LoadOptions(
        downscale=downscale,
        test_every=test_every,
        linearize=linearize,
        max_views=max_views,
        allow_outside_root=allow_outside_root,
    )
    root, found = _resolve(path)
    if format is not None:
        if format not in _LOADERS:
            raise ValueError(f"unknown format {format!r}; expected one of {FORMATS}")
        fmt = format
    else:
        fmt = found[0]
    scene = _LOADERS[fmt](root, opts)
    others = [f for f in found if f != fmt]
    if others:
        scene.meta.setdefault("warnings", []).append(
            f"folder also looks like {', '.join(others)}; loaded it as {fmt} "
            "(pass format= to choose)"
        )
    scene.meta["downscale"] = downscale
    return scene


__all__ = ["FORMATS", "detect_format", "load_scene"]
