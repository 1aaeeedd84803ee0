"""The scene planner: decide, record and let users override which parts a scene needs.

Decisions made before training (from the capture alone): multi-view neighbours per
view, background handling, mesh extraction and whether the masks' hull bounds the mesh.
The environment map / deferred shading and the SH degree need evidence of view
dependence, which needs geometry: they are decided at the end of the RGB-only phase
(the env map is not used before then anyway) by warping training views into their
neighbours through the phase-1 depth and comparing how much the *captured* colours of
the same surface point differ with how much the *view-independent model's* colours
differ (its difference is pure misregistration). A part decided off is never built or
computed. The plan itself (what is decided) is :class:`core.model.plan.ScenePlan`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch

from core.config import ConfigError, TrainConfig
from core.evaluation.metrics import to_display
from core.model.plan import OVERRIDABLE, PAPER_ENVMAP_RESOLUTION, Decision, ScenePlan
from core.render.depth_geometry import (
    DEPTH_FACING_DEG,
    OBLIQUE_DEPTH_MAX_DEG,
    bilinear_lookup,
)
from core.render.gaussians import Gaussians
from core.render.gbuffer import render_gbuffer
from core.scene.cameras import Camera
from core.scene.views import Scene, View
from core.training.mask_agreement import MAX_UNSUPPORTED, unsupported_rim_share
from core.training.view_coverage import unfaced_share

# Two readings of view dependence, both "captured minus view-independent model" over
# surface points seen by a view and its neighbour (sRGB units):
# - excess: mean |Δcolour|. Separates diffuse from everything else, but a few
#   highlights on a textured surface barely move a mean.
# - highlight fraction: share of points whose colour changes by more than
#   HIGHLIGHT_DELTA, i.e. highlights and reflections moving across the surface.
# Measured at the end of a 500-iteration RGB phase, 32 view pairs, alpha > 0.5
# (2026-11-22, antialiased splatting). Generated spheres (32 views, 32 px, 2 samples
# per pixel, seeds 0-3): diffuse excess 0.0003-0.0015, highlights 0.0000-0.0002;
# glossy 0.018-0.021, 0.067-0.076; mirror 0.014-0.015, 0.10. Dev scenes at 128 px:
# spot_plastic (textured cow, glossy coat) 0.0077, 0.031; teapot_gold 0.081, 0.28;
# sphere_mirror 0.094, 0.31. With 8 pairs and alpha > 0.9 the mirror sphere's reading
# fell to 0.003-0.006 over too few pixels; hence more pairs and the lower alpha.
SPECULAR_EXCESS = 0.01
SPECULAR_HIGHLIGHTS = 0.01
HIGHLIGHT_DELTA = 0.1
MILD_EXCESS = 0.005
PROBE_PAIRS = 32
PROBE_MIN_ALPHA = 0.5
# Auto env-map resolution: the paper's 6×128×128 map went with 800-px images taken
# with NeRF-synthetic's lens (f ≈ 1111 px). A reflection sweeps the map at a rate
# proportional to the focal length, so texels per pixel stay the same when the face
# size scales with f. Rounded up to a power of two, within these bounds. At 64 px
# (f ≈ 89) this gives 16; on teapot_gold that scored 24.2 dB test PSNR at 1500
# iterations against 22.3 dB with a 128 map, whose texels each saw too few pixels
# and learned speckle.
PAPER_FOCAL_PX = 1111.1
ENVMAP_AUTO_MIN, ENVMAP_AUTO_MAX = 8, 128
# A capture "never faces some side" when more than this share of normal directions has
# no view within DEPTH_FACING_DEG of face-on (core.training.view_coverage): above the
# sampling's noise, far below the 5-13% of the upper-hemisphere, LLFF and NeRF-synthetic
# layouts; a sphere of views scores 0.
MAX_UNFACED = 0.01


def decide_envmap(plan: ScenePlan, evidence: dict[str, Any], cfg: TrainConfig) -> None:
    """Turn the view-dependence probe into the env-map and SH decisions."""
    if not plan.envmap.pending:
        return
    excess = evidence.get("excess")
    highlights = evidence.get("highlight_fraction", 0.0)
    if excess is None or not math.isfinite(excess):
        plan.envmap = Decision(True, "no usable view pairs to measure: kept on", evidence)
        plan.sh_degree = Decision(cfg.sh_degree, "kept (no evidence)", evidence)
    elif highlights >= SPECULAR_HIGHLIGHTS or excess >= SPECULAR_EXCESS:
        plan.envmap = Decision(
            True, f"specular: {highlights:.1%} of surface points change colour by more "
            f"than {HIGHLIGHT_DELTA} across views beyond misregistration "
            f"(≥ {SPECULAR_HIGHLIGHTS:.0%}), mean excess {excess:.4f} "
            f"(≥ {SPECULAR_EXCESS} also counts)", evidence)  # fmt: skip
        plan.sh_degree = Decision(cfg.sh_degree, "view-dependent scene", evidence)
    elif excess >= MILD_EXCESS:
        plan.envmap = Decision(
            False, f"mildly view-dependent (mean excess {excess:.4f}, highlights "
            f"{highlights:.2%}): SH colour suffices", evidence)  # fmt: skip
        plan.sh_degree = Decision(cfg.sh_degree, "mild view dependence: SH kept", evidence)
    else:
        plan.envmap = Decision(
            False, f"diffuse: mean excess {excess:.4f} < {MILD_EXCESS}, highlights "
            f"{highlights:.2%} < {SPECULAR_HIGHLIGHTS:.0%}", evidence)  # fmt: skip
        plan.sh_degree = Decision(0, "no view dependence: SH degree 0", evidence)
    decide_roughness(plan)
    _apply_overrides(plan, cfg, only=("envmap", "sh_degree", "roughness"))


def plan_roughness(cfg: TrainConfig) -> Decision:
    """Before training: roughness goes with the env map, unless the ablation drops it."""
    if not cfg.ablation.deferred_shading:
        return Decision(False, "no deferred shading (ablation): nothing reflects")
    if not cfg.ablation.roughness:
        return Decision(False, "switched off by the ablation config (mirror lookups, Eq. 9)")
    return Decision(True, "to be decided with the env map", pending=True)


def decide_roughness(plan: ScenePlan) -> None:
    """With the env map decided: roughness where there are reflections to blur."""
    if not plan.roughness.pending:
        return
    if plan.envmap.value:
        plan.roughness = Decision(
            True, "the env map is on: each splat's roughness sets how blurred its "
            "reflection is (mip level of the env map)", plan.envmap.evidence)  # fmt: skip
    else:
        plan.roughness = Decision(False, "no env map: nothing to blur", plan.envmap.evidence)


def find_neighbours(
    cameras: list[Camera], max_angle_deg: float, min_baseline: float
) -> list[tuple[int | None, float]]:
    """Per camera, the other camera with the smallest angle between optical axes.

    Cameras at (almost) the same position give no parallax and are not neighbours.
    Returns (index or None, angle in degrees) per camera.
    """
    if len(cameras) < 2:
        return [(None, math.nan)] * len(cameras)
    fwd = torch.stack([c.forward for c in cameras])
    ctr = torch.stack([c.center for c in cameras])
    cos = (fwd @ fwd.T).clamp(-1, 1)
    ang = torch.rad2deg(torch.acos(cos))
    dist = torch.cdist(ctr, ctr)
    ang = torch.where(dist > min_baseline, ang, torch.full_like(ang, math.inf))
    ang.fill_diagonal_(math.inf)
    best = ang.min(dim=1)
    out: list[tuple[int | None, float]] = []
    for a, j in zip(best.values.tolist(), best.indices.tolist(), strict=True):
        out.append((j, a) if a <= max_angle_deg else (None, a))
    return out


def check_overrides(cfg: TrainConfig) -> None:
    """Raise ConfigError for a ``plan_overrides`` entry no plan can take (unknown part,
    wrong type), before anything is planned or trained."""
    for key, value in cfg.plan_overrides.items():
        if key not in OVERRIDABLE:
            raise ConfigError(
                f"config: field 'plan_overrides.{key}': unknown plan part "
                f"(expected one of {', '.join(OVERRIDABLE)})"
            )
        if key == "sh_degree" and (not isinstance(value, int) or not 0 <= value <= 3):
            raise ConfigError("config: field 'plan_overrides.sh_degree': expected 0..3")
        if key != "sh_degree" and not isinstance(value, bool):
            raise ConfigError(f"config: field 'plan_overrides.{key}': expected true or false")


def _apply_overrides(
    plan: ScenePlan, cfg: TrainConfig, only: tuple[str, ...] = OVERRIDABLE
) -> None:
    check_overrides(cfg)
    for key, value in cfg.plan_overrides.items():
        if key not in only:
            continue
        old: Decision = getattr(plan, key)
        setattr(
            plan,
            key,
            Decision(
                value, f"set by the user (plan said {old.value}: {old.reason})", old.evidence, True
            ),
        )


def auto_envmap_resolution(focal_px: float) -> int:
    """Cube face size with the paper's texels per pixel at this focal length (see top)."""
    if not (math.isfinite(focal_px) and focal_px > 0):
        return PAPER_ENVMAP_RESOLUTION
    r = PAPER_ENVMAP_RESOLUTION * focal_px / PAPER_FOCAL_PX
    r = 2 ** math.ceil(math.log2(r) - 1e-6) if r > 1 else 1
    return int(min(max(r, ENVMAP_AUTO_MIN), ENVMAP_AUTO_MAX))


def plan_envmap_resolution(focals_px: list[float], cfg: TrainConfig) -> Decision:
    """The env map's face size: from the config, or scaled with the median focal length."""
    if cfg.envmap_resolution != "auto":
        return Decision(int(cfg.envmap_resolution), "from the config (envmap_resolution)")
    f = float(torch.tensor(focals_px).median()) if focals_px else math.nan
    r = auto_envmap_resolution(f)
    return Decision(
        r,
        f"the paper's {PAPER_ENVMAP_RESOLUTION} texels at f = {PAPER_FOCAL_PX:.0f} px, "
        f"scaled to this capture's f = {f:.1f} px (power of two in "
        f"[{ENVMAP_AUTO_MIN}, {ENVMAP_AUTO_MAX}])",
        {"median_focal_px": f},
    )


def plan_scene(scene: Scene, cfg: TrainConfig) -> ScenePlan:
    """Decisions that need only the capture; env map and SH stay pending."""
    cams = [v.camera for v in scene.train]
    nbs = find_neighbours(cams, cfg.loss.multiview_max_angle_deg, 1e-3 * scene.radius)
    with_nb = sum(1 for j, _ in nbs if j is not None)
    angles = [a for j, a in nbs if j is not None]
    mv_evidence = {
        "views": len(cams),
        "views_with_neighbour": with_nb,
        "max_angle_deg": cfg.loss.multiview_max_angle_deg,
        "median_neighbour_angle_deg": float(torch.tensor(angles).median()) if angles else None,
    }
    silhouette = decide_silhouette(scene, cfg)
    every_view_masked = all(v.mask is not None for v in scene.train)
    mv = decide_multi_view(cfg, with_nb, len(cams), every_view_masked, silhouette, mv_evidence)
    if scene.has_masks:
        reason = f"alpha/masks present: composite over {cfg.background}"
        if cfg.halo_weight > 0:
            reason += f"; coverage beyond them penalised (loss.mask = {cfg.halo_weight:g})"
        bg = Decision("masked", reason, {})
    else:
        bg = Decision("unmasked", "no alpha or masks: images used as they are", {})
    if cfg.ablation.deferred_shading:
        env = Decision(True, "to be measured at the end of the RGB phase", pending=True)
        sh = Decision(cfg.sh_degree, "to be measured with the env map", pending=True)
    else:
        env = Decision(False, "switched off by the ablation config (SH colour only)")
        sh = Decision(cfg.sh_degree, "from the config")
    if cfg.outputs.mesh:
        mesh = Decision(True, "outputs.mesh is on (the default): the run ends with a mesh")
    else:
        mesh = Decision(False, "switched off by outputs.mesh (`glint mesh` makes one later)")
    plan = ScenePlan(
        env, sh, mv, bg, mesh, [j for j, _ in nbs], envmap_resolution=plan_envmap_resolution(
            [float(c.intrinsics.fx) for c in cams], cfg), silhouette=silhouette,
        roughness=plan_roughness(cfg), hull=decide_hull(scene),
        oblique_depth=decide_oblique_depth(scene, cfg),
    )  # fmt: skip
    _apply_overrides(plan, cfg)
    if not plan.envmap.pending:  # the user set the env map: no probe will decide roughness
        decide_roughness(plan)
    return plan


def decide_multi_view(
    cfg: TrainConfig, with_neighbour: int, views: int, every_view_masked: bool,
    silhouette: Decision, evidence: dict[str, Any],
) -> Decision:  # fmt: skip
    """L_multi (Eq. 12–14) where views have neighbours, unless every view is masked and
    silhouette points pin the surface: there it cost CD, PSNR and normals on all six
    rendered dev scenes (validation split included) and ~30% of the training time
    (docs/benchmarks.md, issue 36). ``plan_overrides.multi_view`` puts it back."""
    if not cfg.ablation.multi_view:
        return Decision(False, "switched off by the ablation config", evidence)
    if with_neighbour == 0:
        return Decision(False, "no view has a neighbour within the angle limit", evidence)
    # a user's silhouette override counts: without the points nothing else pins it
    sil_on = bool(cfg.plan_overrides.get("silhouette", silhouette.value))
    if sil_on and every_view_masked:
        reason = (
            "every view has a mask and silhouette points pin the surface: on such "
            "captures L_multi cost accuracy and ~30% of the training time "
            f"(docs/benchmarks.md); {with_neighbour}/{views} views have a neighbour, "
            "plan_overrides.multi_view=true uses them"
        )
        return Decision(False, reason, evidence)
    return Decision(True, f"{with_neighbour}/{views} views have a neighbour", evidence)


def decide_oblique_depth(scene: Scene, cfg: TrainConfig) -> Decision:
    """L_single on oblique pixels too (60-80° from face-on, with Eq. 5's depth there)
    where the capture never faces some side of the object: there the facing-only rule
    leaves those sides with no depth loss at all, and Eq. 8's depth, which divides by
    N·r̃, is least accurate exactly at the angles they are seen from. A sphere of views
    faces every side, and there the extra pixels cost accuracy (teapot_gold CD +0.8%),
    so it stays off. ``plan_overrides.oblique_depth`` overrides it."""
    centres = [v.camera.center for v in scene.train]
    share = unfaced_share(torch.stack(centres) if centres else torch.empty(0, 3), scene.center)
    evidence = {"unfaced_share": share, "max_unfaced": MAX_UNFACED}
    if not (cfg.ablation.oblique_depth and cfg.ablation.planar_depth):
        what = "oblique_depth" if cfg.ablation.planar_depth else "planar_depth (Eq. 5 depth)"
        return Decision(False, f"switched off by the ablation config ({what})", evidence)
    if not cfg.ablation.facing_depth:
        return Decision(False, "the depth losses already read every angle", evidence)
    measured = (
        f"{share:.1%} of the surface's normal directions face no training view within "
        f"{DEPTH_FACING_DEG:g}°"
    )
    if share > MAX_UNFACED:
        return Decision(
            True, f"{measured} (> {MAX_UNFACED:.0%}): L_single also reads the pixels seen "
            f"{DEPTH_FACING_DEG:g}-{OBLIQUE_DEPTH_MAX_DEG:g}° from face-on, with Eq. 5's "
            "depth there", evidence)  # fmt: skip
    return Decision(
        False, f"{measured} (≤ {MAX_UNFACED:.0%}): every side is faced by some view, "
        "L_single stays on facing pixels", evidence)  # fmt: skip


def decide_hull(scene: Scene) -> Decision:
    """Meshes bounded by the masks' hull where the masks agree with each other
    (core.training.mask_agreement: on rendered captures; off on photo masks, whose
    intersection cuts the object). ``plan_overrides.hull`` and ``glint mesh --hull /
    --no-hull`` override it."""
    evidence = unsupported_rim_share(scene)
    share = evidence["share"]
    if share is None:
        return Decision(False, "fewer than two views have masks: no hull", evidence)
    measured = (
        f"{share:.2%} of the rays one pixel inside the {evidence['views']} masks' "
        "silhouettes miss the intersection of all masks"
    )
    if share <= MAX_UNSUPPORTED:
        return Decision(
            True, f"the masks agree ({measured}, ≤ {MAX_UNSUPPORTED:.0%}): the mesh is "
            "bounded by their hull (membranes across holes and slabs over thin parts go)",
            evidence)  # fmt: skip
    return Decision(
        False, f"the masks disagree ({measured}, > {MAX_UNSUPPORTED:.0%}): their hull "
        "would cut the object, so meshes are not bounded by it", evidence)  # fmt: skip


def decide_silhouette(scene: Scene, cfg: TrainConfig) -> Decision:
    """Silhouette points (core.training.silhouette) where at least two views have masks;
    the points themselves are found when training starts."""
    masked = sum(1 for v in scene.train if v.mask is not None)
    evidence = {"masked_views": masked, "views": len(scene.train)}
    if not cfg.ablation.silhouette:
        return Decision(False, "switched off by the ablation config", evidence)
    if cfg.loss.silhouette <= 0:
        return Decision(False, "loss.silhouette is 0", evidence)
    if masked < 2:
        return Decision(False, "fewer than two views have alpha or masks", evidence)
    reason = (
        f"{masked}/{len(scene.train)} views have masks: their silhouettes give surface "
        "points that pin the surface where fitting alpha alone would shrink it"
    )
    return Decision(True, reason, evidence)


@torch.no_grad()
def probe_view_dependence(
    views: Sequence[View],
    gaussians: Gaussians,
    cfg: TrainConfig,
    radius: float,
    *,
    iteration: int,
    max_pairs: int = PROBE_PAIRS,
) -> dict[str, Any]:
    """Measure colour variation of the same surface across views (see module doc).

    ``views`` are the training views (images on the Gaussians' device), ``radius`` the
    scene's; ``iteration`` is only recorded with the evidence.
    """
    cams = [v.camera for v in views]
    nbs = find_neighbours(cams, 45.0, 1e-3 * radius)
    pairs = [(i, j) for i, (j, _) in enumerate(nbs) if j is not None]
    if len(pairs) > max_pairs:
        step = len(pairs) / max_pairs
        pairs = [pairs[int(k * step)] for k in range(max_pairs)]
    gt_diffs, model_diffs, pixels = [], [], 0
    for i, j in pairs:
        vi, vj = views[i], views[j]
        gi, gj = (
            render_gbuffer(
                gaussians, v.camera, sh_degree=0, backend=cfg.backend,
                antialiased=cfg.antialiased, lowpass=cfg.lowpass_2d, with_roughness=False,
                splat_order=cfg.splat_order,
            )[0]
            for v in (vi, vj)
        )  # fmt: skip
        ok = gi.depth_valid & (gi.alpha > PROBE_MIN_ALPHA)
        if vi.mask is not None:
            ok = ok & (vi.mask > 0.9)
        idx = ok.reshape(-1).nonzero()[:, 0]
        if idx.numel() == 0:
            continue
        W = vi.width
        uv = torch.stack([(idx % W).float() + 0.5, (idx // W).float() + 0.5], dim=-1)
        P = vi.camera.backproject(uv, gi.depth.reshape(-1)[idx])
        uv_j, z_j = vj.camera.project(P)
        d_j, inside = bilinear_lookup(gj.depth, uv_j)
        a_j, _ = bilinear_lookup(gj.alpha, uv_j)
        vis = inside & (z_j > 0) & ((d_j - z_j).abs() < 0.02 * z_j) & (a_j > PROBE_MIN_ALPHA)
        if vj.mask is not None:
            m_j, _ = bilinear_lookup(vj.mask, uv_j)
            vis = vis & (m_j > 0.9)
        if int(vis.sum()) < 16:
            continue

        def warp(img: torch.Tensor, uv_j=uv_j, vis=vis) -> torch.Tensor:
            return torch.stack([bilinear_lookup(img[..., c], uv_j[vis])[0] for c in range(3)], -1)

        base_i = gi.base / gi.alpha.clamp_min(1e-6)[..., None]
        base_j = gj.base / gj.alpha.clamp_min(1e-6)[..., None]
        sel = idx[vis]
        gt_i = vi.image.reshape(-1, 3)[sel]
        mod_i = base_i.reshape(-1, 3)[sel]
        gt_diffs.append((to_display(gt_i) - to_display(warp(vj.image))).abs().mean(-1))
        model_diffs.append((to_display(mod_i) - to_display(warp(base_j))).abs().mean(-1))
        pixels += int(vis.sum())
    if not gt_diffs:
        return {"pairs": 0, "pixels": 0, "excess": None}
    g = torch.cat(gt_diffs)
    m = torch.cat(model_diffs)
    return {
        "pairs": len(gt_diffs),
        "pixels": pixels,
        "iteration": iteration,
        "captured_variation": float(g.mean()),
        "model_variation": float(m.mean()),
        "excess": float(g.mean() - m.mean()),
        "highlight_fraction": float(
            (g > HIGHLIGHT_DELTA).float().mean() - (m > HIGHLIGHT_DELTA).float().mean()
        ),
    }
