"""Structure from motion: cameras and poses for photos that come without them (pycolmap).

``run_sfm(images, out)`` extracts SIFT features, matches pairs chosen by image count
(:mod:`.pairs`), maps incrementally (:mod:`.mapping`), undistorts and writes a COLMAP
scene that :func:`core.scene.formats.load_scene` reads, with a registration report
(:mod:`.report`). :mod:`.align` scores recovered cameras against known ones.
"""

from core.scene.sfm.errors import SfmCancelledError, SfmError
from core.scene.sfm.pipeline import SfmOptions, SfmResult, run_sfm

__all__ = ["SfmCancelledError", "SfmError", "SfmOptions", "SfmResult", "run_sfm"]
