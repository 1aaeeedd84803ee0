"""Poses from verified matches: incremental (or global) mapping, then a second chance.

Incremental mapping adds an image once ≥ 30 of its features see triangulated
points. An image whose only strong match is another not-yet-registered image (two
photos taken after a jump in viewpoint) is left out even though its matches tie it
to the model; on the goldcape capture 2 of 119 photos end up so. The second pass
continues from the largest model with a lower registration minimum (20 inliers)
and two-view tracks kept, so such images join; bundle adjustment and COLMAP's
reprojection filter still vet them. 20, not COLMAP's pair minimum of 15: on a
thinned goldcape capture (90 of its 119 photos, evenly spread) 15 let one photo in 14°
off, 20 did not, and both rescue the full capture's two (docs/benchmarks.md).
Images that still do not register are reported by name.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from core.scene.sfm.colmap_lib import pycolmap
from core.scene.sfm.errors import SfmCancelledError

MAPPERS = ("incremental", "global")
RESCUE_MIN_INLIERS = 20  # the first pass needs 30; 15 admitted a wrong pose (see above)


@dataclass
class MappingResult:
    """The largest model, the sizes of all models found, and who joined late."""

    reconstruction: Any  # pycolmap.Reconstruction
    model_sizes: list[int]
    rescued: list[str] = field(default_factory=list)

    @property
    def registered(self) -> set[str]:
        return {im.name for im in self.reconstruction.images.values() if im.has_pose}


def _incremental_options(seed: int, *, relaxed: bool):
    o = pycolmap.IncrementalPipelineOptions()
    o.random_seed = seed
    o.mapper.random_seed = seed
    o.triangulation.random_seed = seed
    if relaxed:
        o.multiple_models = False
        o.mapper.abs_pose_min_num_inliers = RESCUE_MIN_INLIERS
        o.triangulation.ignore_two_view_tracks = False
    return o


def _run_incremental(
    database: Path,
    image_dir: Path,
    out: Path,
    options: Any,
    *,
    input_path: Path | None,
    on_image: Callable[[], None] | None,
    should_stop: Callable[[], bool] | None,
) -> dict[int, Any]:
    token = pycolmap.CancellationToken()

    def next_image() -> None:
        if on_image:
            on_image()
        if should_stop and should_stop():
            token.cancel()

    out.mkdir(parents=True, exist_ok=True)
    recs = pycolmap.incremental_mapping(
        database,
        image_dir,
        out,
        options,
        input_path=str(input_path) if input_path else "",
        next_image_callback=next_image,
        cancellation_token=token,
    )
    if token.is_cancelled:
        raise SfmCancelledError("structure from motion cancelled during mapping")
    return recs


def _run_global(database: Path, image_dir: Path, out: Path, seed: int) -> dict[int, Any]:
    o = pycolmap.GlobalPipelineOptions()
    o.random_seed = seed
    o.mapper.random_seed = seed
    out.mkdir(parents=True, exist_ok=True)
    return pycolmap.global_mapping(database, image_dir, out, o)


def map_images(
    database: Path,
    image_dir: Path,
    names: Sequence[str],
    work_dir: Path,
    *,
    mapper: str = "incremental",
    seed: int = 0,
    match_more: Callable[[list[str]], None] | None = None,
    on_image: Callable[[], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> MappingResult:
    """Map, keep the largest model, and give unregistered images a second chance.

    ``match_more(names)``: matches the named images against all others before the
    second pass (the pair selection may have skipped the pairs they need).
    """
    if mapper not in MAPPERS:
        raise ValueError(f"unknown mapper {mapper!r}; expected one of {MAPPERS}")
    pycolmap.set_random_seed(seed)
    if mapper == "global":
        recs = _run_global(database, image_dir, work_dir / "global", seed)
    else:
        recs = _run_incremental(
            database,
            image_dir,
            work_dir / "incremental",
            _incremental_options(seed, relaxed=False),
            input_path=None,
            on_image=on_image,
            should_stop=should_stop,
        )
    sizes = sorted((r.num_reg_images() for r in recs.values()), reverse=True)
    if not recs:
        return MappingResult(pycolmap.Reconstruction(), [])
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    result = MappingResult(best, sizes)
    missing = [n for n in names if n not in result.registered]
    if not missing or best.num_reg_images() < 2:
        return result
    if match_more is not None:
        match_more(missing)
    seeded = work_dir / "largest"
    seeded.mkdir(parents=True, exist_ok=True)
    best.write(seeded)
    recs2 = _run_incremental(
        database,
        image_dir,
        work_dir / "second",
        _incremental_options(seed, relaxed=True),
        input_path=seeded,
        on_image=on_image,
        should_stop=should_stop,
    )
    if recs2:
        best2 = max(recs2.values(), key=lambda r: r.num_reg_images())
        if best2.num_reg_images() > best.num_reg_images():
            before = result.registered
            result = MappingResult(best2, sizes)
            result.rescued = sorted(result.registered - before)
    return result
