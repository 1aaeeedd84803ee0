"""Is L_single's target right where it pulls? (issue 21)

Eq. 11 pulls each pixel's rendered normal toward the normal of the rendered depth
(Eq. 10, central differences). Where the depth map is not locally a plane (a
self-occlusion edge inside the object's mask, a crease, a thin part one or two pixels
wide) that target is wrong, and the loss tilts normals and bends depth toward it.
For every view of a split this measures, against the scene's GT normal maps: the
angle of the rendered normal and of the depth normal to the truth, per pixel, and
how L_single's weight (edge weight × (1 − n·N)) is shared between pixels whose
target is good and pixels whose target is off, with the GT depth's own
discontinuities (a neighbour's GT depth jumping by more than ``--jump`` of the
pixel's depth) marked.

    python -m bench.single_view_target RUN --scene ../shared/data/spot_plastic
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np

from bench.trained_run import open_run_and_scene, run_scene_parser
from core.model.trained import TrainedModel
from core.render.depth_geometry import normals_from_depth
from core.scene.groundtruth import load_ground_truth
from core.training.losses import edge_weight

ANGLE_BINS = (0.0, 5.0, 10.0, 20.0, 45.0, 180.0)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)
    b = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


def gt_jumps(depth: np.ndarray, mask: np.ndarray, rel: float) -> np.ndarray:
    """Pixels whose GT depth differs from a 4-neighbour's by more than ``rel``·depth,
    or that touch the silhouette: where no plane through 3×3 pixels fits the truth."""
    H, W = depth.shape
    jump = np.zeros((H, W), bool)
    for dy, dx in ((0, 1), (1, 0)):
        a = depth[: H - dy, : W - dx]
        b = depth[dy:, dx:]
        ma, mb = mask[: H - dy, : W - dx], mask[dy:, dx:]
        j = (ma != mb) | (ma & mb & (np.abs(a - b) > rel * np.minimum(a, b)))
        jump[: H - dy, : W - dx] |= j
        jump[dy:, dx:] |= j
    return jump


def measure(
    model: TrainedModel, scene, root: Path, split: str, rel: float, jump_ratio: float | None = None
) -> dict:
    views = scene.test if split == "test" else scene.train
    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("ren", "dep", "w", "pull", "jump")}
    for v in views:
        gt = load_ground_truth(root, v)
        if gt is None:
            continue
        gb = model.render(v.camera, ("depth", "normal")).gbuffer
        valid = gb.depth_valid & gt.mask.to(gb.depth_valid.device)
        N, ok = normals_from_depth(gb.depth, valid, v.camera, jump_ratio)
        R = v.camera.R.to(gb.normal.dtype)
        n_gt = (gt.normal_world.to(R.dtype) @ R.T).numpy()
        ok = ok.numpy()
        n_ren = gb.normal.detach().numpy()
        n_dep = N.detach().numpy()
        target = v.composited(model.background.cpu())
        w = edge_weight(target.to(gb.normal.dtype)).numpy()
        nr = n_ren / np.maximum(np.linalg.norm(n_ren, axis=-1, keepdims=True), 1e-12)
        pull = w * (1.0 - (nr * n_dep).sum(-1))
        jump = gt_jumps(gt.depth.numpy(), gt.mask.numpy(), rel)
        rows["ren"].append(_angle(n_ren, n_gt)[ok])
        rows["dep"].append(_angle(n_dep, n_gt)[ok])
        rows["w"].append(w[ok])
        rows["pull"].append(pull[ok])
        rows["jump"].append(jump[ok])
    ren, dep, w, pull, jump = (np.concatenate(rows[k]) for k in ("ren", "dep", "w", "pull", "jump"))
    total = float(pull.sum()) or 1.0
    out: dict = {
        "pixels": int(ren.size),
        "rendered_normal_err_deg": {"mean": float(ren.mean()), "median": float(np.median(ren))},
        "depth_normal_err_deg": {"mean": float(dep.mean()), "median": float(np.median(dep))},
        "gt_jump_share_of_pixels": float(jump.mean()),
        "gt_jump_share_of_pull": float(pull[jump].sum() / total),
        "by_depth_normal_err": [],
    }
    for lo, hi in itertools.pairwise(ANGLE_BINS):
        sel = (dep >= lo) & (dep < hi)
        out["by_depth_normal_err"].append({
            "deg": f"[{lo:g}, {hi:g})",
            "pixel_share": float(sel.mean()),
            "pull_share": float(pull[sel].sum() / total),
            "mean_edge_weight": float(w[sel].mean()) if sel.any() else float("nan"),
            "rendered_err_deg": float(ren[sel].mean()) if sel.any() else float("nan"),
            "gt_jump_share": float(jump[sel].mean()) if sel.any() else float("nan"),
        })  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> None:
    ap = run_scene_parser(__doc__)
    ap.add_argument("--split", choices=("train", "test"), default="train")
    ap.add_argument("--jump", type=float, default=0.02, help="relative GT depth jump")
    ap.add_argument(
        "--jump-ratio", type=float, default=None,
        help="one-sided differences where one step is this many times the other "
        "(the trainer uses SAME_SURFACE_JUMP_RATIO; default: central differences)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    model, scene = open_run_and_scene(args)
    out = measure(model, scene, args.scene, args.split, args.jump, args.jump_ratio)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
