"""Do a capture's masks agree with each other? The measurement behind the plan's mesh hull.

The mesh's mask hull (``glint mesh --hull``, ``core.meshing.tsdf`` ``hull_dist``) lifts
every voxel some view's mask puts outside the object. It is only right when every mask
holds the whole object: a real capture's masks (segmentation slips, pose error) each
miss a little, and their intersection erodes the object (goldcape_llff,
docs/benchmarks.md). A pixel one pixel inside a view's silhouette looks at the object, so
its ray must cross the intersection of every view's mask somewhere; rays are marched
through the scene's sphere and each sample tested against all masks
(:func:`core.training.init_points.inside_hull` with every view required). The share of
rays that never enter the intersection is how much the masks disagree: 0–0.16% on the
ten rendered dev captures, 37% on goldcape's photo masks.

The scene plan makes the same measurement (core.training.mask_agreement) and bounds meshes
by the hull at ≤ 2%; this prints it for any captures, e.g. to see why a plan left it off.

    python -m bench.mask_agreement ../shared/data/teapot_gold ../shared/data/goldcape_llff:2
"""

from __future__ import annotations

import argparse

from core.scene.formats import load_scene
from core.training.mask_agreement import RAYS_PER_VIEW, unsupported_rim_share


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", help="scene folders, each optionally :DOWNSCALE (>= 1)")
    ap.add_argument("--rays", type=int, default=RAYS_PER_VIEW, help="rays per masked view")
    args = ap.parse_args(argv)
    print(f"{'scene':<40} {'views':>5} {'rays':>6} {'unsupported':>11} {'worst view':>10}")
    for spec in args.scenes:
        path, _, ds = spec.partition(":")
        m = unsupported_rim_share(
            load_scene(path, downscale=float(ds or 1)), rays_per_view=args.rays
        )
        if m["share"] is None:
            print(f"{path:<40} {m['views']:>5} fewer than two masked views")
            continue
        share, worst = m["share"], m["worst_view"]
        print(f"{path:<40} {m['views']:>5} {m['rays']:>6} {share:>11.4f} {worst:>10.4f}")


if __name__ == "__main__":
    main()
