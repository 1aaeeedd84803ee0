"""Photos taken at different exposures, found from their EXIF before training.

Glint's model has one radiance field and no per-photo exposure, so a capture shot
in automatic mode, where the camera changed shutter, aperture or ISO between
photos, turns those brightness steps into view-dependent colour (on a shiny object
they look like reflections). Loaders call :func:`exposure_warning` and put what it
says into the scene's warnings (``glint validate`` and the API show them); photos
without EXIF exposure tags are not judged.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import OpenImageIO as oiio

# Cameras step exposure in thirds of a stop; anything below is the same exposure.
STOP_TOLERANCE = 1.0 / 3.0
_ISO_KEYS = ("Exif:PhotographicSensitivity", "Exif:ISOSpeedRatings", "ISOSpeedRatings")


def read_exposure(path: Path) -> tuple[float, str] | None:
    """log2 of the light a pixel value stands for (t · ISO / N²) and a readable
    "1/60 s f/4 ISO 200", or None when the header lacks shutter time."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        return None
    try:
        spec = inp.spec()
        t = spec.getattribute("ExposureTime")
        n = spec.getattribute("FNumber")
        iso = next((v for k in _ISO_KEYS if (v := spec.getattribute(k)) is not None), None)
    finally:
        inp.close()
    try:
        t = float(t)
    except (TypeError, ValueError):
        return None
    if not (math.isfinite(t) and t > 0):
        return None
    gain = math.log2(t)
    text = f"1/{round(1 / t)} s" if t < 1 else f"{t:g} s"
    try:
        n = float(n)
        if n > 0:
            gain -= 2 * math.log2(n)
            text += f" f/{n:g}"
    except (TypeError, ValueError):
        pass
    try:
        iso_v = float(iso[0] if isinstance(iso, tuple | list) else iso)
        if iso_v > 0:
            gain += math.log2(iso_v / 100)
            text += f" ISO {iso_v:g}"
    except (TypeError, ValueError, IndexError):
        pass
    return gain, text


def exposure_warning(paths: Sequence[Path]) -> str | None:
    """A warning naming the brightest and darkest photos when their exposures differ by
    more than a third of a stop; None when they agree or carry no exposure tags."""
    found = [(e, p) for p in paths if (e := read_exposure(p)) is not None]
    if len(found) < 2:
        return None
    (lo, lo_text), lo_path = min(found, key=lambda x: x[0][0])
    (hi, hi_text), hi_path = max(found, key=lambda x: x[0][0])
    if hi - lo <= STOP_TOLERANCE + 1e-6:
        return None
    differ = sum(1 for (g, _), _ in found if g - lo > STOP_TOLERANCE + 1e-6)
    return (
        f"exposure differs by {hi - lo:.1f} stops across the photos, from {lo_path.name} "
        f"({lo_text}) to {hi_path.name} ({hi_text}); {differ} of {len(found)} photos are "
        "more than 1/3 stop brighter than the darkest. The model assumes one exposure, so "
        "the steps become view-dependent colour: shoot with fixed (manual) exposure"
    )
