"""How well a run recovered the lighting: its learned env map against the scene's true one.

Only the directions the training views actually reflect can be learned (a mirror
shows each view the part of the environment behind it, nothing else), so the maps
are compared over those: every covered pixel of every training view reflects its
ray about the surface normal (the GT normal maps where the scene ships them, else
the model's own normals), and both maps are sampled there.

Lighting is recovered up to one global exposure factor: w_r, the base colour and the
capture's exposure all trade against the map's brightness. The factor is the
least-squares one in the space the score is taken in: display (sRGB of radiance
clipped at 1) at the exposure the photos were taken at, found by a one-dimensional
search, so a highlight the photos clip does not drive it. Reported: PSNR after that
factor, the Pearson correlation of log luminance (scale-free, HDR-aware), the factor
itself and the share of the sphere of directions that was seen.

The true map is ``envmap.exr`` in the scene folder, a lat-long image in the dev
data's convention (``core.render.envmap_io.LatLong``); ``meta.json:envmap.scale`` is
the exposure it was rendered with, reported beside the fitted factor when present.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from core.model.trained import TrainedModel
from core.render.envmap import EnvMap
from core.render.envmap_io import LatLong, sample_equirect
from core.render.shading import reflect
from core.scene.groundtruth import load_ground_truth
from core.scene.imageio import linear_to_srgb, read_image
from core.scene.views import View

ENVMAP_FILE = "envmap.exr"
MAX_DIRECTIONS = 200_000
SURFACE_ALPHA = 0.5  # model-normal fallback: pixels covered at least this much
_LUMA = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)
# Solid-angle bins for the seen fraction: 64 x 32 lat-long cells weighted by sin(theta).
_COVER_W, _COVER_H = 64, 32


@dataclass
class TrueEnvmap:
    """The environment a scene was rendered with: a lat-long radiance image."""

    image: Tensor  # (H, W, 3) linear radiance, float32
    latlong: LatLong
    scale: float | None  # the exposure it was rendered with (meta.json), when known
    path: Path

    def sample(self, dirs: Tensor) -> Tensor:
        return sample_equirect(self.image, dirs.to(self.image.dtype), self.latlong)


def load_true_envmap(scene_root: str | Path | None) -> TrueEnvmap | None:
    """``envmap.exr`` of a scene folder (and its exposure from meta.json), or None."""
    if scene_root is None:
        return None
    root = Path(scene_root)
    path = root / ENVMAP_FILE
    if not path.is_file():
        return None
    rgb, _ = read_image(path)
    img = rgb.float()
    scale = None
    meta = root / "meta.json"
    if meta.is_file():
        try:
            value = json.loads(meta.read_text()).get("envmap", {}).get("scale")
            scale = float(value) if value is not None else None
        except (json.JSONDecodeError, AttributeError, TypeError, ValueError):
            scale = None
    return TrueEnvmap(img, LatLong(), scale, path)


@torch.no_grad()
def reflected_directions(
    views: Sequence[View],
    scene_root: str | Path | None,
    model: TrainedModel | None = None,
    *,
    max_directions: int = MAX_DIRECTIONS,
    seed: int = 0,
) -> tuple[Tensor, str]:
    """World directions (M, 3) the views' covered pixels reflect, and the normals' source.

    GT normal maps are used where the scene has them for every view ('gt'); otherwise
    the model's rendered normals over pixels it covers ('model'). At most
    ``max_directions`` are kept (an even random subset).
    """
    gen = torch.Generator().manual_seed(seed)
    out: list[Tensor] = []
    source = "gt"
    gts = [load_ground_truth(scene_root, v) if scene_root is not None else None for v in views]
    if any(g is None for g in gts):
        if model is None:
            raise ValueError("no GT normal maps for these views and no model to render normals")
        source = "model"
    per_view = max(1, max_directions // max(len(views), 1))
    for v, gt in zip(views, gts, strict=True):
        _, rays = v.camera.world_rays(dtype=torch.float32, device="cpu")
        if source == "gt":
            assert gt is not None
            normals, covered = gt.normal_world.float(), gt.mask
        else:
            assert model is not None
            frame = model.render(v.camera, ("normal",))
            normals = frame.world_normals().float().cpu()
            covered = frame.gbuffer.alpha.cpu() > SURFACE_ALPHA
        d = reflect(rays[covered], normals[covered])
        d = d[torch.isfinite(d).all(-1) & (d.norm(dim=-1) > 0.5)]
        if len(d) > per_view:
            d = d[torch.randperm(len(d), generator=gen)[:per_view]]
        out.append(d)
    dirs = torch.cat(out) if out else torch.zeros(0, 3)
    return dirs, source


def seen_fraction(dirs: Tensor) -> float:
    """Share of the sphere of directions (by solid angle) that ``dirs`` fall in."""
    if len(dirs) == 0:
        return 0.0
    row, col = LatLong(rows="centers").to_pixel(dirs.double(), _COVER_H, _COVER_W)
    r = row.round().long().clamp(0, _COVER_H - 1)
    c = torch.remainder(col.round().long(), _COVER_W)
    hit = torch.zeros(_COVER_H, _COVER_W, dtype=torch.bool)
    hit[r, c] = True
    theta = (torch.arange(_COVER_H, dtype=torch.float64) + 0.5) / _COVER_H * math.pi
    w = theta.sin()[:, None].expand(_COVER_H, _COVER_W)
    return float((w * hit).sum() / w.sum())


def _psnr(a: Tensor, b: Tensor) -> float:
    return 10.0 * math.log10(1.0 / max(float(((a - b) ** 2).mean()), 1e-20))


def _display(x: Tensor) -> Tensor:
    return linear_to_srgb(x.clamp(0.0, 1.0))


def exposure_fit(learned: Tensor, true: Tensor, photo_exposure: float = 1.0) -> float:
    """The factor s (learned ≈ s·true) that best matches the two maps in display space
    at the photos' exposure k: display(k·learned/s) against display(k·true).

    Golden-section search on log s around the linear least-squares start, bracketed a
    factor 1000 either way; the error is unimodal in s for non-negative radiance in
    practice. Scoring at the photos' exposure weighs what the photos could show: a
    highlight they clip does not drive the factor, and neither does a dark region
    they crush.
    """
    lt, tt = learned.double(), true.double()
    den = float((tt * tt).sum())
    if den <= 0:
        return 1.0
    start = max(float((lt * tt).sum()) / den, 1e-12)
    td = _display(tt * photo_exposure)

    def err(log_s: float) -> float:
        return float(((_display(lt * (photo_exposure / math.exp(log_s))) - td) ** 2).mean())

    lo, hi = math.log(start) - math.log(1000.0), math.log(start) + math.log(1000.0)
    g = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = err(a), err(b)
    for _ in range(80):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = err(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = err(b)
    return math.exp(0.5 * (lo + hi))


def log_luminance_correlation(learned: Tensor, true: Tensor) -> float:
    """Pearson correlation of log luminance (a floor of 1e-3 × the mean avoids log 0)."""
    la = learned.double() @ _LUMA
    lb = true.double() @ _LUMA
    la = torch.log(la.clamp_min(1e-3 * float(la.mean().clamp_min(1e-12))))
    lb = torch.log(lb.clamp_min(1e-3 * float(lb.mean().clamp_min(1e-12))))
    a, b = la - la.mean(), lb - lb.mean()
    den = float(a.norm() * b.norm())
    return float((a * b).sum()) / den if den > 0 else math.nan


@torch.no_grad()
def compare_envmaps(envmap: EnvMap, truth: TrueEnvmap, dirs: Tensor) -> dict[str, Any]:
    """PSNR (display space at the photos' exposure, after the exposure fit) and
    log-luminance correlation of the learned map against the true one over ``dirs``;
    the fitted factor and coverage; and the PSNR after one factor per colour channel. The
    photos' exposure is the one the scene records (``meta.json:envmap.scale``), else 1."""
    if len(dirs) == 0:
        return {"error": "no reflected directions (no covered pixels)"}
    learned = envmap.sample(dirs.to(envmap.log_radiance)).double().cpu()
    true = truth.sample(dirs).double().cpu()
    k = truth.scale if truth.scale is not None else 1.0
    s = exposure_fit(learned, true, k)
    # per channel too: Eq. 9's w_r is one number, so a coloured metal's tint (gold's
    # Fresnel reflectance) can only live in the map; these gains take it out
    gains = [exposure_fit(learned[:, c], true[:, c], k) for c in range(learned.shape[1])]
    tinted = learned * (k / torch.tensor(gains, dtype=learned.dtype))
    out = {
        "psnr": _psnr(_display(learned * (k / s)), _display(true * k)),
        "psnr_channel_gains": _psnr(_display(tinted), _display(true * k)),
        "log_correlation": log_luminance_correlation(learned, true),
        "exposure": s,
        "channel_gains": gains,
        "seen_fraction": seen_fraction(dirs),
        "directions": len(dirs),
    }
    if truth.scale is not None:
        out["true_exposure"] = truth.scale
    return out


COMPARISON_PICTURE = "envmap_vs_true.png"


def envmap_accuracy(
    model: TrainedModel,
    views: Sequence[View],
    scene_root: str | Path | None,
    picture_dir: Path | None = None,
) -> dict[str, Any] | None:
    """The run's env-map score against ``scene_root/envmap.exr`` (and the side-by-side
    picture in ``picture_dir``), or None when either map is missing (no true map in
    the scene, or the run learned none)."""
    truth = load_true_envmap(scene_root)
    if truth is None or model.envmap is None:
        return None
    dirs, source = reflected_directions(views, scene_root, model)
    out = compare_envmaps(model.envmap, truth, dirs)
    out["normals"] = source
    if picture_dir is not None and "exposure" in out:
        save_envmap_comparison(
            Path(picture_dir) / COMPARISON_PICTURE, model.envmap, truth, dirs, out["exposure"]
        )
        out["picture"] = COMPARISON_PICTURE
    return out


def specular_share(model: TrainedModel, views: Sequence[View]) -> float | None:
    """Share of the reflection term in the rendered colour of the covered pixels:
    Σ luminance(w_r·E) / Σ luminance(base + w_r·E), linear. None without an env map."""
    if model.envmap is None or not model.phase.envmap:
        return None
    spec_sum = total = 0.0
    for v in views:
        frame = model.render(v.camera, ("specular",))
        gb, sh = frame.gbuffer, frame.shade
        assert sh is not None
        cov = gb.alpha > SURFACE_ALPHA
        luma = _LUMA.to(gb.base)
        spec_sum += float((sh.specular[cov] @ luma).sum())
        total += float(((gb.base[cov] + sh.specular[cov]) @ luma).sum())
    return spec_sum / total if total > 0 else None


def _latlong_panel(values: Tensor, seen: Tensor) -> np.ndarray:
    """Display image (H, W, 3) uint8; directions never reflected are dimmed and greyed."""
    img = _display(values.double()).float()
    grey = img.mean(-1, keepdim=True).expand_as(img)
    img = torch.where(seen[..., None], img, 0.25 * grey + 0.1)
    return (img.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()


def save_envmap_comparison(
    path: str | Path,
    envmap: EnvMap,
    truth: TrueEnvmap,
    dirs: Tensor,
    exposure: float,
    height: int = 128,
) -> Path:
    """Side-by-side lat-long picture, learned (top) over true (bottom), in the true map's
    convention and at the photos' exposure (the learned map divided by the fitted
    ``exposure``); directions no training view reflects are greyed."""
    from PIL import Image

    ll = truth.latlong
    width = 2 * height
    grid = ll.pixel_directions(height, width)
    k = truth.scale if truth.scale is not None else 1.0
    learned = envmap.sample(grid.to(envmap.log_radiance)).cpu() * (k / exposure)
    true = truth.sample(grid) * k
    row, col = ll.to_pixel(dirs.float(), height, width)
    seen = torch.zeros(height, width, dtype=torch.bool)
    r = row.round().long().clamp(0, height - 1)
    c = torch.remainder(col.round().long(), width)
    seen[r, c] = True
    # close one-pixel gaps between sampled directions
    seen = torch.nn.functional.max_pool2d(seen[None, None].float(), 3, 1, 1)[0, 0] > 0
    top = _latlong_panel(learned, seen)
    bottom = _latlong_panel(true, seen)
    gap = np.full((4, width, 3), 255, dtype=np.uint8)
    path = Path(path)
    Image.fromarray(np.concatenate([top, gap, bottom], axis=0)).save(path)
    return path
