"""Every training knob in one validated model, loadable from YAML or JSON.

Iteration marks (phases, densification, SH degree) are given for the paper's
30k-iteration schedule and scale in proportion when ``iterations`` differs, so a
short CPU run keeps the same shape as the full one.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from core.errors import GlintError

REFERENCE_ITERATIONS = 30_000
# The variance of a uniform distribution over one pixel: a Gaussian stand-in for the box
# filter a camera pixel applies (Mip-Splatting's 2D filter is 0.1 for the same reason).
PIXEL_BOX_VARIANCE = 1.0 / 12.0
# Upper bounds of the config's numbers: far beyond any sensible run, well inside what
# the engine (int64 counters, float32 tensors, a database integer) can hold.
MAX_ITERATIONS = 10_000_000
MAX_GAUSSIANS = 50_000_000
MAX_INIT_POINTS = 10_000_000
MAX_LOSS_WEIGHT = 1e6
MAX_LEARNING_RATE = 1.0
MAX_SEED = 2**32 - 1
MAX_TIME_BUDGET_S = 7 * 24 * 3600  # a week: beyond it a budget is a typo, not a plan
_DURATION_RE = re.compile(r"(\d+(?:\.\d+)?)\s*(h|m|s)")
_DURATION_UNITS = {"h": 3600.0, "m": 60.0, "s": 1.0}


class ConfigError(GlintError):
    """A config file or value is invalid; the message names the file and field."""


class _Strict(BaseModel):
    # NaN and ±Infinity are refused everywhere: no knob of the method means them
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class Phases(_Strict):
    """Marks on the paper's 30k schedule (scaled to the run's length)."""

    geometry_start: int = Field(
        3_000, ge=0, le=MAX_ITERATIONS, description="single-view loss and env map on"
    )
    multiview_start: int = Field(7_000, ge=0, le=MAX_ITERATIONS, description="multi-view loss on")
    sh_full_start: int = Field(
        10_000, ge=0, le=MAX_ITERATIONS, description="SH degree 0 until here, then max"
    )
    min_rgb_iterations: int = Field(
        500,
        ge=0,
        le=MAX_ITERATIONS,
        description="short runs: RGB-only phase at least this long (≤ 1/3 of the run)",
    )
    min_geometry_iterations: int = Field(
        250,
        ge=0,
        le=MAX_ITERATIONS,
        description="short runs: single-view phase at least this long (≤ 1/6 of the run)",
    )
    geometry_pause_after_reset: int = Field(
        100,
        ge=0,
        le=MAX_ITERATIONS,
        description="iterations after each opacity reset without L_single and L_multi "
        "(every Gaussian is near-transparent, so the depth they constrain is undefined)",
    )
    silhouette_until: float = Field(
        1.0,
        gt=0,
        le=1,
        description="fraction of the run that keeps the silhouette-point loss (1.0: to the "
        "end); ending it earlier (0.8) settles bulky objects' images better, but thin parts "
        "and smooth mirrors shrink without it (docs/benchmarks.md, 2026-11-30)",
    )

    @model_validator(mode="after")
    def _ordered(self) -> Phases:
        if self.multiview_start < self.geometry_start:
            raise ValueError("multiview_start must be >= geometry_start")
        return self


class LossWeights(_Strict):
    """Eq. 15–16 weights and the multi-view thresholds."""

    l1: float = Field(0.8, ge=0, le=1, description="L_rgb = l1·L1 + (1 - l1)·D-SSIM")
    scale: float = Field(
        100.0, ge=0, le=MAX_LOSS_WEIGHT, description="λ2, Eq. 7 (scales measured in scene radii)"
    )
    single_view: float = Field(0.2, ge=0, le=MAX_LOSS_WEIGHT, description="λ3, Eq. 11")
    multi_view: float = Field(0.1, ge=0, le=MAX_LOSS_WEIGHT, description="λ4, Eq. 14")
    multiview_max_angle_deg: float = Field(30.0, gt=0, le=180)
    multiview_max_error_px: float = Field(1.0, gt=0, le=10_000)
    multiview_pixels: int = Field(
        4096, ge=16, le=1 << 24, description="pixels sampled per multi-view step"
    )
    single_view_edge_aware: bool = Field(
        True, description="weight L_single by PGSR's (1 - image gradient)^2"
    )
    multiview_error_weighting: bool = Field(
        True, description="weight L_multi pixels by PGSR's exp(-reprojection error)"
    )
    silhouette: float = Field(
        0.05,
        ge=0,
        le=MAX_LOSS_WEIGHT,
        description="weight of the silhouette-point depth loss (mean |error| in pixel "
        "footprints; masked captures only, see core/training/silhouette.py)",
    )
    mask: float = Field(
        2.0,
        ge=0,
        le=MAX_LOSS_WEIGHT,
        description="weight of mean max(alpha − mask, 0) of a masked view, the coverage "
        "beyond its mask (ablation.mask_coverage)",
    )


class LearningRates(_Strict):
    """Adam learning rates (3DGS defaults); positions scale with the scene radius."""

    means_init: float = Field(1.6e-4, gt=0, le=MAX_LEARNING_RATE)
    means_final: float = Field(1.6e-6, gt=0, le=MAX_LEARNING_RATE)
    sh_dc: float = Field(2.5e-3, gt=0, le=MAX_LEARNING_RATE)
    sh_rest: float = Field(2.5e-3 / 20, gt=0, le=MAX_LEARNING_RATE)
    opacity: float = Field(0.025, gt=0, le=MAX_LEARNING_RATE)
    scales: float = Field(5e-3, gt=0, le=MAX_LEARNING_RATE)
    quats: float = Field(1e-3, gt=0, le=MAX_LEARNING_RATE)
    refl: float = Field(0.01, gt=0, le=MAX_LEARNING_RATE)
    roughness: float = Field(0.01, gt=0, le=MAX_LEARNING_RATE, description="as w_r's logits")
    envmap: float = Field(0.01, gt=0, le=MAX_LEARNING_RATE)


class Densification(_Strict):
    """3DGS adaptive density control (marks on the 30k schedule)."""

    enabled: bool = True
    start: int = Field(500, ge=0, le=MAX_ITERATIONS)
    stop: int = Field(15_000, ge=0, le=MAX_ITERATIONS)
    interval: int = Field(100, ge=1, le=MAX_ITERATIONS)
    grad_threshold: float = Field(
        2e-4, gt=0, le=1, description="mean view-space gradient, NDC units"
    )
    percent_dense: float = Field(
        0.01, gt=0, le=1, description="clone below, split above (× radius)"
    )
    prune_opacity: float = Field(0.005, ge=0, lt=1)
    opacity_reset_interval: int = Field(3_000, ge=0, le=MAX_ITERATIONS, description="0 disables")
    max_screen_size: float = Field(
        0.15, gt=0, le=10, description="prune when 2D radius > this × image"
    )
    max_gaussians: int = Field(300_000, ge=1, le=MAX_GAUSSIANS)
    seed_behind: float = Field(
        0.0,
        ge=0,
        le=1,
        description="at each opacity reset, splats proposed behind the rendered surface on "
        "the worst-explained pixels' rays, inside the masks' hull, as a share of the "
        "Gaussians there are (0: none)",
    )
    prune_hidden: bool = Field(
        False,
        description="at each opacity reset, remove the splats that lie behind the rendered "
        "surface in every training view",
    )
    absgrad: bool = Field(
        False,
        description="AbsGS: densify on the per-pixel absolute screen gradient (cuda backend "
        "only; use a larger grad_threshold, e.g. 8e-4)",
    )


class Ablation(_Strict):
    """Switches of the paper's Table 3/4 (all on = the full method)."""

    deferred_shading: bool = True
    planar_depth: bool = Field(True, description="False: conventional blended depth (Eq. 5)")
    single_view: bool = True
    multi_view: bool = True
    planar: bool = Field(True, description="False: full covariance (no scale loss)")
    silhouette: bool = Field(
        True,
        description="False: no silhouette points (the paper's method has none; Glint adds "
        "them because fitting alpha alone shrinks surfaces by their splats' blur)",
    )
    one_sided: bool = Field(
        True,
        description="False: two-sided splats (the paper's); True: each splat learns which "
        "side it is seen from and views behind it cull it (core/render/orientation.py)",
    )
    grazing_opacity: bool = Field(
        True,
        description="False: opacity is the same from every angle (the paper's); True: each "
        "splat learns how much to fade when seen nearly edge-on, so splats piled up along "
        "grazing rays stop blurring silhouettes outwards (core/render/grazing.py)",
    )
    same_surface_normals: bool = Field(
        True,
        description="False: L_single's depth normals by central differences everywhere (the "
        "paper's); True: one-sided differences across depth jumps, so a pixel at a "
        "self-occlusion edge is not pulled toward a normal of neither surface "
        "(core/render/depth_geometry.py)",
    )
    facing_depth: bool = Field(
        True,
        description="False: L_single and L_multi use every covered pixel (the paper's); "
        "True: only pixels whose surface faces the view within 60° (Eq. 8's depth is "
        "ill-conditioned edge-on; core/render/depth_geometry.py)",
    )
    oblique_depth: bool = Field(
        True,
        description="False: the depth losses never take oblique pixels; True: where the "
        "capture never faces some side of the object (views from above or the front only), "
        "the scene plan lets L_single also read pixels seen 60-80° from face-on, through "
        "Eq. 5's centre depth (core/training/view_coverage.py)",
    )
    silhouette_holds_normals: bool = Field(
        True,
        description="True: the silhouette term's gradient moves the splats and their "
        "blending but never turns their normals (it knows where the surface is, not how "
        "it is oriented; four more G-buffer channels in its phases); False: through Eq. "
        "8's full gradient, which tilts the normals the deferred shading reflects with",
    )
    silhouette_touching: bool = Field(
        True,
        description="True: a silhouette ray only has to reach the surface: of the points "
        "along its chord through the masks' hull, the term holds the one the rendered "
        "surface comes closest to (core/training/silhouette.py); False: the chord's "
        "middle, which over a sharp edge or a concavity hangs in the air and pulls the "
        "surface out to it",
    )
    roughness: bool = Field(
        True,
        description="False: every splat reflects one direction (the paper's Eq. 9, a mirror "
        "lookup); True: each splat learns a roughness and reads the env map's mip chain at "
        "the level it gives (core/render/roughness.py, core/render/envmap_mips.py)",
    )
    fresnel: bool = Field(
        True,
        description="False: w_r is the same from every angle (the paper's Eq. 9); True: "
        "the reflection rises towards grazing angles (Schlick's Fresnel from a head-on "
        "reflectance the scene learns with its env map, lowered for rough surfaces) and "
        "takes its light from the base colour, so bright rims need no bent normals "
        "(core/render/fresnel.py)",
    )
    mask_coverage: bool = Field(
        True,
        description="False: coverage is fitted only through the colours composited over the "
        "background (the paper's); True: masked views also pay for rendered coverage "
        "beyond the mask (loss.mask), which sees a halo whatever the colours",
    )


class Evaluation(_Strict):
    every: int = Field(
        0, ge=0, le=MAX_ITERATIONS, description="iterations between evaluations; 0 = ~20 per run"
    )
    views: int = Field(
        4, ge=1, le=1000, description="held-out views evaluated at each cadence point"
    )


class Outputs(_Strict):
    mesh: bool = Field(
        True,
        description="end the run with a coloured TSDF mesh (mesh.ply/.glb/.obj); the scene "
        "plan records it and plan_overrides.mesh replaces it",
    )
    mesh_color: Literal["base", "radiance"] = Field(
        "base",
        description="vertex colour: 'base' (the material without reflections) or "
        "'radiance' (the rendered colour, environment baked in)",
    )
    mesh_resolution: int = Field(
        256, ge=16, le=2048, description="voxels along the longest side of the surface's box"
    )
    asset: bool = Field(
        False,
        description="also export a relightable asset (asset.glb with baked PBR textures, "
        "asset_env.exr/.hdr; docs/asset.md); it is made from the mesh, so the run meshes",
    )
    asset_faces: int = Field(
        100_000, ge=100, le=5_000_000, description="face budget of the asset's mesh"
    )
    asset_texture_size: int = Field(
        1024, ge=16, le=8192, description="asset texture size, a power of two"
    )

    @field_validator("asset_texture_size")
    @classmethod
    def _power_of_two(cls, value: int) -> int:
        if value & (value - 1):
            raise ValueError(f"{value} is not a power of two (e.g. 512, 1024, 2048)")
        return value


class TrainConfig(_Strict):
    """The whole training configuration."""

    iterations: int = Field(
        30_000,
        ge=1,
        le=MAX_ITERATIONS,
        description="iterations of the run; with time_budget, whichever comes first ends it",
    )
    time_budget: float | None = Field(
        None,
        description="training time budget: seconds, or '90s', '5m', '1h', '1h30m' (at most 7 "
        "days); the phase schedule is fitted to it from the measured step time and the run "
        "ends with complete outputs when it is spent. Outputs (export, mesh) come after it",
    )
    seed: int = Field(0, ge=0, le=MAX_SEED)
    device: str = Field("cpu", description="'cpu', 'cuda' or 'cuda:N'")
    backend: Literal["auto", "reference", "cpu", "cuda"] = "auto"
    resolution_scale: float = Field(1.0, gt=0, le=1, description="downscale images on load")
    background: Literal["white", "black", "random"] | list[float] = "white"
    sh_degree: int = Field(3, ge=0, le=3)
    antialiased: bool = Field(
        True,
        description="scale opacity by the 2D low-pass compensation (Mip-Splatting; gsplat's "
        "'antialiased' mode) so edge-on planar Gaussians fade instead of blurring silhouettes",
    )
    lowpass_2d: float = Field(
        PIXEL_BOX_VARIANCE,
        ge=0,
        le=10,
        description="variance (px²) of the screen-space low-pass filter added to every "
        "splat's 2D covariance: 1/12, a pixel's box filter, which is what a photo's pixel "
        "integrates (3DGS uses 0.3; wider filters blur silhouettes outwards and training "
        "then shrinks the surface to match them)",
    )
    splat_order: Literal["auto", "centre", "slab", "plane"] = Field(
        "auto",
        description="order splats are composited in at each pixel: 'plane', where the "
        "pixel's ray meets each splat's plane (core/render/raster/plane_order.py; cpu and "
        "reference backends), so a surface's colours and normals are not weighted toward "
        "the splats whose centres lie toward the camera; 'centre', by centre depth (3DGS, "
        "every backend); 'auto' (default), plane order where the backend has it, centre "
        "order on cuda (gsplat sorts by itself); 'slab', centre depth rounded up to slabs "
        "two median splat sizes thick (an experiment; docs/benchmarks.md)",
    )
    envmap_resolution: int | Literal["auto"] = Field(
        "auto",
        description="cube face size in texels; auto: the paper's 128 at its focal length "
        "(≈1111 px), scaled with this capture's focal length (see the scene plan)",
    )
    # 5,000, the issue-36 protocol's start, rather than 20,000: densification grows what
    # the surface needs either way; the larger start ended with 11-19% more Gaussians
    # (every one paid for in every later step) and no better surface or image on four
    # rendered scenes, two of them validation (docs/benchmarks.md, 2026-11-28)
    init_points: int = Field(
        5_000,
        ge=1,
        le=MAX_INIT_POINTS,
        description="points of the first model when the scene has no cloud (inside the "
        "masks' visual hull, else random in the bounds)",
    )
    # Off by default: 0.3 took rocker_gold_256's CD×10² from 1.05 to 0.76 and the
    # validation fandisk's from 1.18 to 0.97, but teapot_gold's from 0.42 to 0.84 (its
    # flat, dark, textureless bottom came out hollow) and the mirror sphere's from 0.44
    # to 1.43; docs/benchmarks.md, 2026-11-29
    init_volume_fraction: float = Field(
        0.0,
        ge=0,
        le=1,
        description="share of the visual-hull init points placed inside the hull (on "
        "random samples of their rays) instead of on its surface; helps objects with "
        "deep concavities, hurts flat textureless faces",
    )
    init_opacity: float = Field(0.1, gt=0, lt=1)
    init_refl: float = Field(0.05, ge=0, lt=1)
    init_roughness: float = Field(
        0.15, gt=0, lt=1, description="initial per-splat roughness ρ (GGX α = ρ²)"
    )
    phases: Phases = Phases()
    loss: LossWeights = LossWeights()
    lr: LearningRates = LearningRates()
    densify: Densification = Densification()
    ablation: Ablation = Ablation()
    eval: Evaluation = Evaluation()
    outputs: Outputs = Outputs()
    checkpoint_every: int = Field(
        0, ge=0, le=MAX_ITERATIONS, description="iterations; 0 = ~5 per run + phase ends"
    )
    plan_overrides: dict[str, Any] = Field(default_factory=dict)

    @field_validator("time_budget", mode="before")
    @classmethod
    def _time_budget(cls, v: Any) -> Any:
        return None if v is None else parse_duration(v)

    @field_validator("envmap_resolution")
    @classmethod
    def _envmap_res(cls, v: Any) -> Any:
        if v != "auto" and not 4 <= int(v) <= 2048:
            raise ValueError("envmap_resolution must be 'auto' or an integer in [4, 2048]")
        return v

    @field_validator("device")
    @classmethod
    def _device(cls, v: str) -> str:
        # Only the spelling here: whether the device exists is the training machine's
        # business (the API validates jobs on a server that may have no GPU).
        from core.devices import DEVICE_HINT, DEVICE_RE

        if not DEVICE_RE.match(v):
            raise ValueError(f"expected {DEVICE_HINT}, got '{v}'")
        return v

    @field_validator("background")
    @classmethod
    def _bg(cls, v: Any) -> Any:
        if isinstance(v, list) and (len(v) != 3 or not all(0.0 <= float(x) <= 1.0 for x in v)):
            raise ValueError("background as a list must be 3 values in [0, 1]")
        return v

    def scaled(self, mark: int) -> int:
        """A mark on the 30k schedule mapped onto this run's length."""
        return round(mark * self.iterations / REFERENCE_ITERATIONS)

    @property
    def halo_weight(self) -> float:
        """The halo term's weight on a masked view: ``loss.mask``, or 0 where
        ``ablation.mask_coverage`` is off (the trainer and the plan's record read this one
        rule)."""
        return self.loss.mask if self.ablation.mask_coverage else 0.0


def parse_duration(value: Any) -> float:
    """Seconds from ``90``, ``"90s"``, ``"5m"``, ``"1h"`` or ``"1h30m"``; ValueError
    naming what was expected otherwise (zero, negative, non-finite, over a week)."""
    expected = "a duration such as 90s, 5m, 1h or 1h30m (or a number of seconds)"
    if isinstance(value, bool):
        raise ValueError(f"expected {expected}, got {value!r}")
    if isinstance(value, int | float):
        seconds = float(value)
    elif isinstance(value, str):
        text = value.strip().lower().replace(" ", "")
        try:
            seconds = float(text)
        except ValueError:
            parts = _DURATION_RE.findall(text)
            if not text or "".join(n + u for n, u in parts) != text:
                raise ValueError(f"expected {expected}, got {value!r}") from None
            units = [u for _, u in parts]
            if len(set(units)) != len(units):
                raise ValueError(f"expected {expected}, got {value!r} (a unit twice)") from None
            seconds = sum(float(n) * _DURATION_UNITS[u] for n, u in parts)
    else:
        raise ValueError(f"expected {expected}, got {type(value).__name__}")
    if not math.isfinite(seconds) or seconds <= 0:
        raise ValueError(f"a time budget must be positive and finite, got {value!r}")
    if seconds > MAX_TIME_BUDGET_S:
        raise ValueError(
            f"a time budget is at most {MAX_TIME_BUDGET_S // 86400} days "
            f"({MAX_TIME_BUDGET_S} s), got {value!r} ({seconds:.0f} s)"
        )
    return seconds


def format_duration(seconds: float) -> str:
    """``330`` → ``"5m30s"`` (the inverse of :func:`parse_duration`, for reports)."""
    s = round(seconds)
    h, rest = divmod(s, 3600)
    m, sec = divmod(rest, 60)
    out = (f"{h}h" if h else "") + (f"{m}m" if m else "") + (f"{sec}s" if sec or not s else "")
    return out or "0s"


def _format_errors(exc: ValidationError, source: str) -> str:
    lines = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "(root)"
        lines.append(f"{source}: field '{loc}': {err['msg']}")
    return "\n".join(lines)


def config_from_dict(data: dict[str, Any], source: str = "config") -> TrainConfig:
    try:
        return TrainConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_errors(exc, source)) from None


# Fields added after runs were first saved, with the value those runs trained with.
LEGACY_DEFAULTS: dict[str, Any] = {
    "antialiased": False,
    "lowpass_2d": 0.3,
    "splat_order": "centre",
}


# Ablation switches added after runs were first saved, with the value those runs had.
LEGACY_ABLATION: dict[str, Any] = {"fresnel": False}


def saved_config(data: dict[str, Any], source: str = "saved config") -> TrainConfig:
    """The config of an existing run (config.json or a checkpoint's copy).

    A field the run predates gets the value it actually trained with, not today's
    default: a classic-splatted model rendered antialiased loses its silhouettes.
    """
    merged = {**LEGACY_DEFAULTS, **data}
    ablation = merged.get("ablation")
    if ablation is None or isinstance(ablation, dict):  # anything else: the validator's
        merged["ablation"] = {**LEGACY_ABLATION, **(ablation or {})}
    return config_from_dict(merged, source)


# Fields a run may be resumed with changed: where it runs, and what its export writes
# (a finished run re-exports with the new outputs settings; its training is unchanged).
RESUMABLE_CHANGES = ("device", "backend", "outputs")


def _flat(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """{"a": {"b": 1}} -> {"a.b": 1}."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[prefix + key] = value
    return out


def config_changes(
    old: TrainConfig, new: TrainConfig, ignore: tuple[str, ...] = RESUMABLE_CHANGES
) -> list[str]:
    """Dotted fields whose values differ, as ``field: old -> new`` (``ignore``d prefixes
    left out): what a run folder trained with against what a command now asks for."""
    a, b = _flat(old.model_dump(mode="json")), _flat(new.model_dump(mode="json"))
    changes = []
    for key in sorted(set(a) | set(b)):
        if a.get(key) == b.get(key) or any(key == p or key.startswith(p + ".") for p in ignore):
            continue
        changes.append(f"{key}: {json.dumps(a.get(key))} -> {json.dumps(b.get(key))}")
    return changes


def load_config(path: str | Path | None, overrides: dict[str, Any] | None = None) -> TrainConfig:
    """Read YAML/JSON (or defaults when ``path`` is None) and apply dotted overrides."""
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"{path}: config file not found")
        text = path.read_text()
        try:
            data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text) or {}
        except (json.JSONDecodeError, yaml.YAMLError) as exc:
            raise ConfigError(f"{path}: cannot parse: {exc}") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: expected a mapping at the top level")
    for key, value in (overrides or {}).items():
        node = data
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    return config_from_dict(data, str(path) if path else "config")
