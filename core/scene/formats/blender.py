"""NeRF-synthetic (Blender) scenes: ``transforms_{train,test,val}.json`` + RGBA images.

Poses are OpenGL camera-to-world (camera looks down -z, +y up); intrinsics come from
``camera_angle_x`` (square pixels, centred principal point) unless explicit
``fl_x``/``fl_y``/``cx``/``cy``/``w``/``h`` are given. The split is the files' own.
"""

from __future__ import annotations

import math
from pathlib import Path, PurePosixPath
from typing import Any

from core.errors import SceneError
from core.scene.cameras import Intrinsics
from core.scene.formats.common import (
    IMAGE_EXTS,
    LoadOptions,
    ViewSpec,
    as_float,
    find_image,
    finish,
    image_size,
    load_json,
    opengl_c2w_to_w2c,
    parse_pose,
    require,
    split_every,
    split_label,
)
from core.scene.views import Scene

SPLIT_FILES = ("transforms_train.json", "transforms_test.json", "transforms_val.json")


def view_name(file_path: str) -> str:
    """``./train/r_0.png`` -> ``train/r_0``: unique across splits, no extension."""
    p = file_path.replace("\\", "/")
    while p.startswith("./"):
        p = p[2:]
    q = PurePosixPath(p)
    return str(q.with_suffix("")) if q.suffix.lower() in IMAGE_EXTS else p


def _lookup(key: str, frame: dict | None, top: dict, index: int | None) -> tuple[Any, str] | None:
    """A camera key from the frame (nerfstudio per-frame intrinsics) or the top level."""
    if frame is not None and key in frame:
        return frame[key], f"frames[{index}].{key}"
    if key in top:
        return top[key], key
    return None


def parse_intrinsics(
    top: dict,
    frame: dict | None,
    index: int | None,
    default_size: tuple[int, int] | None,
    *,
    file: Path,
) -> Intrinsics:
    """Intrinsics from ``fl_x``/``fl_y``/``cx``/``cy``/``w``/``h`` or ``camera_angle_x/y``.

    ``default_size`` (from the first image's header) fills in a missing ``w``/``h``.
    """

    def num(key: str, positive: bool = False) -> float | None:
        hit = _lookup(key, frame, top, index)
        return None if hit is None else as_float(hit[0], file=file, field=hit[1], positive=positive)

    w, h = num("w", True), num("h", True)
    if w is None or h is None:
        if default_size is None:
            raise SceneError("image size unknown: give 'w' and 'h'", file=file, field="w")
        w = w if w is not None else float(default_size[0])
        h = h if h is not None else float(default_size[1])
    for key, v in (("w", w), ("h", h)):
        if v != int(v):
            raise SceneError(f"image size must be an integer, got {v}", file=file, field=key)
    width, height = int(w), int(h)

    fx = num("fl_x", True)
    if fx is None:
        ax = num("camera_angle_x", True)
        if ax is None:
            raise SceneError(
                "no focal length: give 'fl_x' or 'camera_angle_x'",
                file=file,
                field="camera_angle_x",
            )
        if ax >= math.pi:
            raise SceneError(
                f"field of view must be below pi, got {ax}", file=file, field="camera_angle_x"
            )
        fx = 0.5 * width / math.tan(0.5 * ax)
    fy = num("fl_y", True)
    if fy is None:
        ay = num("camera_angle_y", True)
        fy = 0.5 * height / math.tan(0.5 * ay) if ay is not None and ay < math.pi else fx
    cx, cy = num("cx"), num("cy")
    return Intrinsics(
        fx, fy, width / 2.0 if cx is None else cx, height / 2.0 if cy is None else cy, width, height
    )


def frame_spec(
    top: dict,
    frame: Any,
    index: int,
    base: Path,
    default_size: tuple[int, int] | None,
    *,
    file: Path,
    confine: bool = True,
) -> ViewSpec:
    """One ``frames[i]`` entry -> ViewSpec (pose validated, image located)."""
    if not isinstance(frame, dict):
        raise SceneError("expected an object", file=file, field=f"frames[{index}]")
    rel = require(frame, "file_path", file=file, field=f"frames[{index}].file_path")
    if not isinstance(rel, str) or not rel:
        raise SceneError(
            "expected a non-empty string", file=file, field=f"frames[{index}].file_path"
        )
    field = f"frames[{index}].transform_matrix"
    raw = require(frame, "transform_matrix", file=file, field=field)
    c2w = parse_pose(raw, file=file, field=field)
    image = find_image(base, rel, file=file, field=f"frames[{index}].file_path", confine=confine)
    has_size = all(_lookup(k, frame, top, index) is not None for k in ("w", "h"))
    if default_size is None and not has_size:
        default_size = image_size(image)
    intr = parse_intrinsics(top, frame, index, default_size, file=file)
    mask = None
    if "mask_path" in frame:
        mask = find_image(
            base,
            str(frame["mask_path"]),
            file=file,
            field=f"frames[{index}].mask_path",
            confine=confine,
        )
    return ViewSpec(
        name=view_name(rel),
        image=image,
        world_to_cam=opengl_c2w_to_w2c(c2w),
        intrinsics=intr,
        mask=mask,
        meta={"source": str(file), "frame": index},
    )


def frames_of(doc: Any, file: Path, allow_empty: bool = False) -> list:
    """The ``frames`` list of a transforms document (non-empty unless ``allow_empty``)."""
    if not isinstance(doc, dict):
        raise SceneError("expected a JSON object at the top level", file=file)
    frames = require(doc, "frames", file=file, field="frames")
    if not isinstance(frames, list):
        raise SceneError("expected a list", file=file, field="frames")
    if not frames and not allow_empty:
        raise SceneError("no frames", file=file, field="frames")
    return frames


def _split_specs(
    root: Path, file: Path, opts: LoadOptions, allow_empty: bool = False
) -> list[ViewSpec]:
    doc = load_json(file)
    frames = frames_of(doc, file, allow_empty)
    if not frames:
        return []
    confine = not opts.allow_outside_root
    first = frames[0] if isinstance(frames[0], dict) else {}
    size = None
    if not all(k in doc for k in ("w", "h")):
        rel = require(first, "file_path", file=file, field="frames[0].file_path")
        field = "frames[0].file_path"
        size = image_size(find_image(root, str(rel), file=file, field=field, confine=confine))
    return [
        frame_spec(doc, fr, i, root, size, file=file, confine=confine)
        for i, fr in enumerate(frames)
    ]


def load(root: Path, opts: LoadOptions) -> Scene:
    """Load a NeRF-synthetic scene folder (``transforms_train.json`` required)."""
    train_file = root / SPLIT_FILES[0]
    if not train_file.is_file():
        raise SceneError("file not found", file=train_file)
    train = _split_specs(root, train_file, opts)
    test_file = next((root / f for f in SPLIT_FILES[1:] if (root / f).is_file()), None)
    meta: dict[str, Any] = {"warnings": []}
    if test_file is not None:
        test = _split_specs(root, test_file, opts, allow_empty=True)
        meta["split"] = f"explicit ({SPLIT_FILES[0]} / {test_file.name})"
    else:
        train, test = split_every(train, opts.test_every)
        meta["split"] = split_label(opts.test_every, "frame") + " (no test file)"
    return finish(train, test, "blender", root, opts, meta=meta)
