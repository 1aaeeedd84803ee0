"""Held-out silhouette agreement of meshes: each mesh drawn into the test views vs their masks.

A capture without a true surface (a real photo capture) still has one check of its mesh that
no training view took part in: the held-out views' object masks. Each mesh is rasterised into
every test view that has a mask (``--supersample``² samples per pixel, coverage ≥ 0.5
counts as object) and compared with the mask (≥ 0.5): intersection over
union, the share of the mask the mesh leaves out (``missing``), and the mesh's coverage
outside the mask as a share of the mask (``extra``). Meshes of one scene are compared on
the same views; that is how the mask hull (``glint mesh --hull``) was judged.

    python -m bench.mask_iou ../shared/data/goldcape_llff runs/a/mesh.ply runs/b/mesh.ply \\
        --downscale 2
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from core.scene.cameras import Camera
from core.scene.formats import load_scene
from core.scene.views import Scene


@dataclass
class MaskAgreement:
    """One mesh against the masks of the views it was drawn into (pixels pooled)."""

    mesh: str
    views: int
    iou: float
    missing: float
    extra: float


def _fill(samples: np.ndarray, tri: np.ndarray, box: int) -> None:
    """Set every sample (integer position) inside one of ``tri`` (N, 3, 2), each of whose
    bounding boxes spans fewer than ``box`` samples, by edge functions on a box² grid."""
    Hs, Ws = samples.shape
    x0 = np.floor(tri[:, :, 0].min(axis=1)).astype(np.int64)
    y0 = np.floor(tri[:, :, 1].min(axis=1)).astype(np.int64)
    k = np.arange(box)
    xs = x0[:, None, None] + k[None, None, :]  # (N, 1, box)
    ys = y0[:, None, None] + k[None, :, None]  # (N, box, 1)
    inside = np.ones((len(tri), box, box), dtype=bool)
    area = (tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1]) - (
        tri[:, 1, 1] - tri[:, 0, 1]
    ) * (tri[:, 2, 0] - tri[:, 0, 0])
    sign = np.sign(area)[:, None, None]
    for a, b in ((0, 1), (1, 2), (2, 0)):
        ax, ay = tri[:, a, 0, None, None], tri[:, a, 1, None, None]
        bx, by = tri[:, b, 0, None, None], tri[:, b, 1, None, None]
        inside &= sign * ((bx - ax) * (ys - ay) - (by - ay) * (xs - ax)) >= 0
    inside &= (xs >= 0) & (xs < Ws) & (ys >= 0) & (ys < Hs)
    n, r, c = np.nonzero(inside)
    samples[y0[n] + r, x0[n] + c] = True


def mesh_coverage(mesh: trimesh.Trimesh, camera: Camera, supersample: int = 4) -> np.ndarray:
    """(H, W) float coverage of each pixel by the mesh's projection, from supersample² samples
    per pixel (sample k of pixel i at i + (k + 0.5) / s, like the pixel centres); a sample
    counts when it lies inside a projected face (edges included)."""
    s = int(supersample)
    H, W = camera.height, camera.width
    uv, z = camera.project(torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float64))
    uv, z = uv.numpy(), z.numpy()
    faces = np.asarray(mesh.faces)
    faces = faces[(z[faces] > 1e-9).all(axis=1)]  # faces wholly in front of the camera
    tri = uv[faces] * s - 0.5  # sample positions become integers
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    keep = (hi[:, 0] >= 0) & (hi[:, 1] >= 0) & (lo[:, 0] < W * s) & (lo[:, 1] < H * s)
    tri, lo, hi = tri[keep], lo[keep], hi[keep]
    span = (np.floor(hi) - np.floor(lo)).max(axis=1) + 1  # samples along the longer side
    samples = np.zeros((H * s, W * s), dtype=bool)
    box = 4
    while len(tri):
        now = span <= box
        sel = np.flatnonzero(now)
        step = max(1, 4_000_000 // (box * box))  # bound the (N, box, box) grid's memory
        for i in range(0, len(sel), step):
            _fill(samples, tri[sel[i : i + step]], box)
        tri, span, box = tri[~now], span[~now], box * 2
    return samples.reshape(H, s, W, s).mean(axis=(1, 3))


def mask_agreement(
    mesh: trimesh.Trimesh, scene: Scene, *, supersample: int = 4, name: str = "mesh"
) -> MaskAgreement:
    """Pool every masked test view's pixels and score the mesh against the masks."""
    views = [v for v in scene.test if v.mask is not None]
    if not views:
        raise ValueError("no test view has a mask to compare the mesh against")
    inter = union = mask_px = miss = extra = 0
    for v in views:
        covered = mesh_coverage(mesh, v.camera, supersample) >= 0.5
        obj = v.mask.numpy() >= 0.5
        inter += int((covered & obj).sum())
        union += int((covered | obj).sum())
        mask_px += int(obj.sum())
        miss += int((obj & ~covered).sum())
        extra += int((covered & ~obj).sum())
    return MaskAgreement(
        mesh=name,
        views=len(views),
        iou=inter / max(union, 1),
        missing=miss / max(mask_px, 1),
        extra=extra / max(mask_px, 1),
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", help="scene folder whose test views have masks")
    ap.add_argument("meshes", nargs="+", help="mesh files (PLY/OBJ/GLB) in the scene's frame")
    ap.add_argument(
        "--downscale",
        type=float,
        default=1.0,
        help="divide the images by this (>= 1), as the run was trained",
    )
    ap.add_argument("--supersample", type=int, default=4)
    ap.add_argument("--json", help="also write the rows here")
    args = ap.parse_args(argv)
    scene = load_scene(args.scene, downscale=args.downscale)
    try:
        rows = [
            mask_agreement(
                trimesh.load(m, force="mesh", process=False),
                scene,
                supersample=args.supersample,
                name=m,
            )
            for m in args.meshes
        ]
    except ValueError as e:
        raise SystemExit(f"{args.scene}: {e}") from e
    print(f"{'mesh':<60} {'views':>5} {'IoU':>7} {'missing':>8} {'extra':>7}")
    for r in rows:
        print(f"{r.mesh:<60} {r.views:>5} {r.iou:7.4f} {r.missing:8.4f} {r.extra:7.4f}")
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(r) for r in rows], indent=2))


if __name__ == "__main__":
    main()
