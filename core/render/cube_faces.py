"""Cube-map faces: the one table every lookup follows.

Torch code (``core.render.envmap``) and the compiled lookups (``shading_compiled``,
``envmap_lookup_compiled``) read the same table; this module imports neither, so both
can import it. (Data only: numba functions are not shared across files, since numba's
on-disk cache does not notice an edit in a function defined in another file.)
"""

from __future__ import annotations

# Per face: (major axis, major sign, sc axis, sc sign, tc axis, tc sign).
FACE_TABLE: tuple[tuple[int, int, int, int, int, int], ...] = (
    (0, +1, 2, -1, 1, -1),
    (0, -1, 2, +1, 1, -1),
    (1, +1, 0, +1, 2, +1),
    (1, -1, 0, +1, 2, -1),
    (2, +1, 0, +1, 1, -1),
    (2, -1, 0, -1, 1, -1),
)
