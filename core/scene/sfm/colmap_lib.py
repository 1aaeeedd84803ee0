"""pycolmap, always imported after OpenImageIO.

pycolmap 4 links its own copy of the image libraries. Imported before the
OpenImageIO wheel, it breaks OpenImageIO's PNG writer: the next PNG written aborts
the process with ``free(): invalid pointer`` (pycolmap 4.2.1, OpenImageIO 3.2.2,
Linux). Imported after it, both work. Every SfM module takes pycolmap from here;
tests/test_sfm.py holds the order in a fresh process.

Where pycolmap is not installed (the GPU acceptance kit leaves its 36 MiB wheel
behind: SfM runs on the CPU, before training), asking for SfM is a clear error.
"""

import OpenImageIO  # noqa: F401  (first: see above)

from core.scene.sfm.errors import SfmError

try:
    import pycolmap
except ImportError as exc:
    raise SfmError(
        "structure from motion needs the pycolmap package, which is not installed here "
        "(pip install pycolmap)"
    ) from exc

__all__ = ["pycolmap"]
