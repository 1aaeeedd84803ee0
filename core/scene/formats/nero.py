"""NeRO scenes: per image ``{k}.png`` and ``{k}-camera.pkl`` = pickle of (pose, K).

``pose`` is a 3x4 world-to-camera matrix in OpenCV axes and ``K`` the 3x3 intrinsics
(NeRO's glossy-synthetic layout). Masks come from the image's alpha, or from
``{k}-mask.png`` when present. Pickles are read with an unpickler that only builds
numpy arrays and plain containers: uploaded scene files must never run code.
"""

from __future__ import annotations

import io
import pickle
import re
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import SceneError
from core.scene.cameras import Intrinsics
from core.scene.formats.common import (
    IMAGE_EXTS,
    LoadOptions,
    ViewSpec,
    as_matrix,
    finish,
    image_size,
    parse_pose,
    split_every,
    split_label,
)
from core.scene.views import Scene

CAMERA_SUFFIX = "-camera.pkl"
_ALLOWED = {
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("_codecs", "encode"),
    ("collections", "OrderedDict"),
}


class _ArrayUnpickler(pickle.Unpickler):
    """Unpickler limited to numpy arrays/scalars: refuses every other global."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in _ALLOWED:
            raise pickle.UnpicklingError(
                f"refusing to load {module}.{name} (only numpy arrays are allowed)"
            )
        if module == "numpy.core.multiarray":  # numpy < 2 pickles; same objects under numpy._core
            module = "numpy._core.multiarray" if hasattr(np, "_core") else module
        return super().find_class(module, name)


def read_camera_pickle(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(validated world-to-camera 4x4, K 3x3) float64 arrays from a NeRO camera pickle."""
    try:
        obj = _ArrayUnpickler(io.BytesIO(path.read_bytes())).load()
    except FileNotFoundError:
        raise SceneError("file not found", file=path) from None
    except Exception as e:  # any decoding failure of an untrusted file is the file's fault
        raise SceneError(f"cannot read camera pickle: {type(e).__name__}: {e}", file=path) from e
    if isinstance(obj, dict) and {"pose", "K"} <= obj.keys():
        obj = (obj["pose"], obj["K"])
    if not isinstance(obj, (tuple, list)) or len(obj) < 2:
        raise SceneError("expected a pickled (pose, K) pair", file=path)
    pose = parse_pose(obj[0], file=path, field="pose")
    K = as_matrix(obj[1], (3, 3), file=path, field="K")
    return pose, K


def intrinsics_from_K(K: np.ndarray, width: int, height: int, *, file: Path) -> Intrinsics:
    """Pinhole intrinsics from a 3x3 K; skew or a non-projective last row is refused."""
    if K[0, 1] != 0 or K[1, 0] != 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise SceneError(
            f"expected K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}",
            file=file,
            field="K",
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise SceneError("focal lengths must be positive", file=file, field="K")
    return Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height)


def _sort_key(key: str) -> tuple:
    """Numeric keys in numeric order (``2`` before ``10``), others by name."""
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", key))


def find_keys(root: Path) -> list[str]:
    return sorted(
        (p.name[: -len(CAMERA_SUFFIX)] for p in root.glob(f"*{CAMERA_SUFFIX}")), key=_sort_key
    )


def _find_file(root: Path, stem: str) -> Path | None:
    for ext in IMAGE_EXTS:
        for e in (ext, ext.upper()):
            if (root / f"{stem}{e}").is_file():
                return root / f"{stem}{e}"
    return None


def load(root: Path, opts: LoadOptions) -> Scene:
    """Load a NeRO folder of ``{k}.png`` + ``{k}-camera.pkl`` (+ ``{k}-mask.png``)."""
    keys = find_keys(root)
    if not keys:
        raise SceneError(f"no *{CAMERA_SUFFIX} files", file=root)
    specs = []
    for k in keys:
        cam_file = root / f"{k}{CAMERA_SUFFIX}"
        w2c, K = read_camera_pickle(cam_file)
        image = _find_file(root, k)
        if image is None:
            raise SceneError(f"image for camera '{k}' not found", file=root / f"{k}.png")
        width, height = image_size(image)
        specs.append(
            ViewSpec(
                name=k,
                image=image,
                world_to_cam=w2c,
                intrinsics=intrinsics_from_K(K, width, height, file=cam_file),
                mask=_find_file(root, f"{k}-mask"),
            )
        )
    train, test = split_every(specs, opts.test_every)
    meta: dict[str, Any] = {"warnings": [], "split": split_label(opts.test_every, "view by key")}
    return finish(train, test, "nero", root, opts, meta=meta)
