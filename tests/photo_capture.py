"""Photos without poses, as a user uploads them: a small generated textured capture.

Twelve views 10° apart on one ring around a textured sphere in a textured room
(``core.scene.textured``), 128x96 PNG with object masks: SfM registers all of them in
about a second, and rendering them takes about as long. Rendered once per process.
"""

from __future__ import annotations

import functools
import tempfile
from pathlib import Path

VIEWS = 12
SIZE = (128, 96)


@functools.cache
def _render(n: int, size: tuple[int, int]) -> tuple[tuple[str, bytes, bytes], ...]:
    from core.scene.imageio import write_image
    from core.scene.textured import render_textured_view, ring_cameras

    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for cam in ring_cameras(36, *size, rings=(25.0,))[:n]:
            rgb, mask = render_textured_view(cam)
            photo = write_image(Path(tmp) / f"{cam.name}.png", rgb)
            m = write_image(Path(tmp) / f"{cam.name}_mask.png", mask, encode_srgb=False)
            out.append((f"{cam.name}.png", photo.read_bytes(), m.read_bytes()))
    return tuple(out)


def photo_files(
    n: int = VIEWS, *, folder: str = "images/", masks: bool = True
) -> list[tuple[str, bytes]]:
    """(path, bytes) of ``n`` photos under ``folder`` (``""``: the top level) and, with
    ``masks``, their masks in ``masks/``."""
    files = []
    for name, photo, mask in _render(n, SIZE):
        files.append((f"{folder}{name}", photo))
        if masks:
            files.append((f"masks/{name}", mask))
    return files


def stray_files(n: int, *, folder: str = "") -> list[tuple[str, bytes]]:
    """``n`` photos of unrelated flat textures (nothing in common with anything):
    ``stray_0.png``, ... (the SfM tests' own)."""
    from tests.test_sfm import unrelated_photos

    with tempfile.TemporaryDirectory() as tmp:
        names = unrelated_photos(Path(tmp), n, SIZE)
        return [(f"{folder}{name}", (Path(tmp) / name).read_bytes()) for name in names]
