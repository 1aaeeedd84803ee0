"""pycolmap, always imported after OpenImageIO.

pycolmap 4 links its own copy of the image libraries. Imported before the
OpenImageIO wheel, it breaks OpenImageIO's PNG writer: the next PNG written aborts
the process with ``free(): invalid pointer`` (pycolmap 4.2.1, OpenImageIO 3.2.2,
Linux). Imported after it, both work. Every SfM module takes pycolmap from here;
tests/test_sfm.py holds the order in a fresh process.
"""

import OpenImageIO  # noqa: F401  (first: see above)
import pycolmap

__all__ = ["pycolmap"]
