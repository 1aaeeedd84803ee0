"""nerfstudio / Instant-NGP scenes: one ``transforms.json`` with all frames.

Poses are OpenGL camera-to-world like Blender's. Intrinsics live at the top level or
per frame (``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``, or ``camera_angle_x``).
Only pinhole images are accepted: a distortion model with any nonzero coefficient
is refused rather than trained on silently wrong rays. The split comes from
``train_filenames``/``test_filenames`` when present, else every ``test_every``-th frame.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from core.errors import SceneError
from core.scene.formats.blender import frame_spec, frames_of, view_name
from core.scene.formats.common import (
    LoadOptions,
    ViewSpec,
    as_float,
    find_image,
    finish,
    image_size,
    load_json,
    require,
    split_every,
    split_label,
)
from core.scene.views import Scene

FILE = "transforms.json"
PINHOLE_MODELS = {"PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL", "FULL_OPENCV"}
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")


def check_camera_model(obj: dict, prefix: str, *, file: Path) -> None:
    """Refuse non-pinhole models and nonzero distortion (``prefix`` locates ``obj``)."""
    if "camera_model" in obj:
        model = str(obj["camera_model"]).upper()
        if model not in PINHOLE_MODELS:
            raise SceneError(
                f"camera model {obj['camera_model']!r} is not a pinhole model; "
                "undistort/reproject the images to PINHOLE first",
                file=file,
                field=f"{prefix}camera_model",
            )
    for key in DISTORTION_KEYS:
        if key in obj:
            v = as_float(obj[key], file=file, field=f"{prefix}{key}")
            if v != 0.0:
                raise SceneError(
                    f"lens distortion is not supported ({key} = {v}); undistort the images "
                    "first (e.g. COLMAP image_undistorter or ns-process-data) and use "
                    "camera_model PINHOLE",
                    file=file,
                    field=f"{prefix}{key}",
                )


def _explicit_split(doc: dict, specs: list[ViewSpec], file: Path) -> tuple[list, list] | None:
    """Use ``train_filenames``/``test_filenames`` (nerfstudio's split lists) when given."""
    if "test_filenames" not in doc and "val_filenames" not in doc:
        return None
    key = "test_filenames" if "test_filenames" in doc else "val_filenames"
    names = doc[key]
    if not isinstance(names, list):
        raise SceneError("expected a list of file paths", file=file, field=key)
    test_names = {view_name(str(n)) for n in names}
    unknown = test_names - {s.name for s in specs}
    if unknown:
        raise SceneError(
            f"lists files that are not frames: {sorted(unknown)[:3]}", file=file, field=key
        )
    train_names = None
    if "train_filenames" in doc and isinstance(doc["train_filenames"], list):
        train_names = {view_name(str(n)) for n in doc["train_filenames"]}
    test = [s for s in specs if s.name in test_names]
    train = [
        s
        for s in specs
        if s.name not in test_names and (train_names is None or s.name in train_names)
    ]
    return train, test


def load(root: Path, opts: LoadOptions) -> Scene:
    """Load a nerfstudio / Instant-NGP ``transforms.json`` scene."""
    file = root / FILE
    doc = load_json(file)
    frames = frames_of(doc, file)
    check_camera_model(doc, "", file=file)
    confine = not opts.allow_outside_root
    size = None
    if not all(k in doc for k in ("w", "h")):
        first = frames[0] if isinstance(frames[0], dict) else {}
        if not all(k in first for k in ("w", "h")):
            rel = require(first, "file_path", file=file, field="frames[0].file_path")
            field = "frames[0].file_path"
            size = image_size(find_image(root, str(rel), file=file, field=field, confine=confine))
    specs = []
    for i, frame in enumerate(frames):
        if isinstance(frame, dict):
            check_camera_model(frame, f"frames[{i}].", file=file)
        specs.append(frame_spec(doc, frame, i, root, size, file=file, confine=confine))
    meta: dict[str, Any] = {"warnings": []}
    split = _explicit_split(doc, specs, file)
    if split is not None:
        train, test = split
        meta["split"] = "explicit (test_filenames)"
    else:
        train, test = split_every(specs, opts.test_every)
        meta["split"] = split_label(opts.test_every, "frame")
    return finish(train, test, "nerfstudio", root, opts, meta=meta)
