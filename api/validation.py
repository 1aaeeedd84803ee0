"""Scene validation with the core loaders: a report, or a problem naming file and field.

The loaders read every image, so a corrupt file anywhere is found here rather than
hours into training. Paths in errors are made relative to the scene folder: users
know their files by those names, and server paths stay private. An upload of plain
photos (no poses, :mod:`api.service.photos`) is a scene too: its photos and masks are
checked here, its cameras are recovered by the jobs' ``sfm`` phase.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from api.problems import ApiError, FieldError
from api.service.photos import find_photos, photos_report

log = logging.getLogger("glint.validation")

PHOTOS_HINT = (
    "plain photos without poses, for structure from motion (at least 3, at the top level "
    "or in images/; masks, if any, in masks/ named like the photos)"
)


def _relative(file: str | None, root: Path) -> str | None:
    if file is None:
        return None
    p = Path(file)
    try:
        rel = p.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:
        return p.name
    return rel if rel != "." else None


def _private(message: str, root: Path, whole: str = ".") -> str:
    """``message`` with the scene folder's server path cut out of any path in it (the
    folder itself named ``whole``)."""
    for prefix in (str(root.resolve()), str(root)):
        message = message.replace(prefix + "/", "").replace(prefix, whole)
    return message


def _report(summary: dict[str, Any]) -> dict[str, Any]:
    res = summary["resolutions"]
    return {
        "format": summary["format"],
        "views": summary["train_views"] + summary["test_views"],
        "train_views": summary["train_views"],
        "test_views": summary["test_views"],
        "resolution": list(res[0]) if res else [],
        "resolutions": [list(r) for r in res],
        "intrinsics": summary["intrinsics_first"],
        "masks": bool(summary["masks"]),
        "points": int(summary["points"]),
        "center": list(summary["center"]),
        "radius": float(summary["radius"]),
        "warnings": list(summary["warnings"]),
        "needs_sfm": False,
    }


def validate_scene(root: Path) -> dict[str, Any]:
    """Load the scene under ``root`` (format detected), or check its photos when it is an
    images-only upload; its report or an :class:`ApiError`."""
    from core.errors import GlintError, SceneError
    from core.scene.formats import load_scene

    try:
        photos = find_photos(root)
        if photos is not None:
            return photos_report(photos)
        scene = load_scene(root)
        return _report(scene.summary())
    except SceneError as exc:
        file = _relative(exc.file, root)
        reason = _private(exc.reason, root)
        if reason.startswith("no known scene format found"):
            reason += f"; or {PHOTOS_HINT}"
        where = f"{file}: " if file else ""
        if exc.field:
            where += f"field '{exc.field}': "
        raise ApiError(
            422,
            "invalid-scene",
            f"{where}{reason}",
            errors=[FieldError(field=exc.field, message=reason, file=file)],
        ) from None
    except GlintError as exc:  # too few photos for structure from motion
        raise ApiError(422, "invalid-scene", _private(str(exc), root, "the upload")) from None
    except Exception as exc:
        # uploads are untrusted: whatever a loader trips on is still the scene's fault
        log.warning("scene under %s failed to load", root, exc_info=True)
        msg = _private(str(exc), root)
        raise ApiError(
            422, "invalid-scene", f"scene could not be loaded: {type(exc).__name__}: {msg}"
        ) from None
