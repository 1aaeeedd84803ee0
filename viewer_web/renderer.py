"""Server-side frames for the viewer: the job's latest checkpoint, rendered deferred.

The model is read straight from ``checkpoint.pt`` (no scene, no optimiser) and read
again whenever the file's mtime changes, so a viewer follows a job while it trains.
Renders run on the GPU when one is present (backend "auto" picks the CUDA rasteriser
there, the compiled CPU one otherwise). Everything here is blocking: callers run it on
worker threads, never on the event loop.
"""

from __future__ import annotations

import io
import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from core.cameras import Camera, Intrinsics
from core.checkpoint import load_checkpoint
from core.config import TrainConfig, saved_config
from core.envmap import EnvMap
from core.envmap_io import cube_to_equirect
from core.gaussians import Gaussians
from core.gbuffer import geometry_depth, render_gbuffer_tensors
from core.imageio import linear_to_srgb
from core.outputs import CHANNELS, colormap
from core.planner import ScenePlan
from core.raster import fallback_backend
from core.schedule import Phase, phase_at
from core.shading import deferred_shade
from core.trainer import CHECKPOINT_NAME, eval_background

log = logging.getLogger("glint.viewer")

__all__ = ["CHANNELS", "LoadedModel", "ModelCache", "encode_jpeg", "render_channel"]


def default_device() -> torch.device:
    """The GPU when there is one: viewers must not compete with training for the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


@dataclass
class LoadedModel:
    """One checkpoint, ready to render: what a frame needs and nothing to train with."""

    gaussians: Gaussians
    envmap: EnvMap | None
    cfg: TrainConfig
    phase: Phase
    iteration: int
    mtime: float
    center: list[float]
    radius: float
    device: torch.device
    static: dict[str, torch.Tensor]
    backend: str = "auto"

    @staticmethod
    def precompute(g: Gaussians, sh_degree: int) -> dict[str, torch.Tensor]:
        """View-independent per-Gaussian inputs, computed once per checkpoint.

        Covariances and normals each cost a quaternion → matrix pass over every
        Gaussian, about a third of a CPU frame on a 100k model; colours too when the
        run has not reached view-dependent SH yet (degree 0).
        """
        static = {
            "means": g.params["means"].detach(),
            "covariances": g.covariances.detach(),
            "opacities": g.opacities.detach(),
            "normals": g.normals().detach(),
            "w_r": g.w_r.detach(),
        }
        if sh_degree == 0:
            dummy = Camera.look_at([0, 0, 1], [0, 0, 0], [0, 1, 0], Intrinsics(1, 1, 0, 0, 1, 1))
            static["colors"] = g.colors(dummy, 0).detach()
        return static

    @property
    def n_gaussians(self) -> int:
        return self.gaussians.num

    def summary(self) -> dict[str, Any]:
        """The ``model`` message: what the client shows and frames its first view with."""
        return {
            "iteration": self.iteration,
            "n_gaussians": self.n_gaussians,
            "phase": self.phase.name,
            "envmap": self.envmap is not None,
            "center": self.center,
            "radius": self.radius,
            "device": str(self.device),
            "backend": self.backend,
        }


def _phase_of(
    extra: dict[str, Any], cfg: TrainConfig, gaussians: Gaussians, has_env: bool
) -> Phase:
    """The phase the run was in at its last iteration (as ``Trainer.current_phase``).

    Checkpoints written by tools other than the trainer may carry no plan: then the
    env map is used if the file holds one, and the model's own SH degree.
    """
    iteration = int(extra.get("iteration", cfg.iterations))
    plan_data = extra.get("plan")
    if isinstance(plan_data, dict):
        plan = ScenePlan.from_dict(plan_data)
        env, mv, sh = (
            bool(plan.envmap.value),
            bool(plan.multi_view.value),
            int(plan.sh_degree.value),
        )
    else:
        env, mv, sh = has_env, False, gaussians.sh_degree
    return phase_at(
        cfg, max(iteration - 1, 0), envmap_planned=env, multi_view_planned=mv, max_sh_degree=sh
    )


def frame_backend(trained_with: str, device: torch.device) -> str:
    """The rasteriser for this server's frames of a run trained with ``trained_with``.

    A run's backend was picked for the machine that trained it: a GPU worker's
    ``cuda`` cannot run on a CPU-only API server, nor ``cpu`` on a GPU one. The run
    is still viewable: a backend this device lacks gives way to ``auto`` here.
    """
    chosen, why = fallback_backend(trained_with, device)
    if why is not None:
        log.info("viewer: %s; rendering with '%s' instead", why, chosen)
    return chosen


def load_model(path: Path, device: torch.device) -> LoadedModel:
    """Read a checkpoint for viewing (weights only; raises CheckpointError if unreadable)."""
    mtime = path.stat().st_mtime
    ck = load_checkpoint(path, device)
    extra = ck.extra
    cfg_data = extra.get("config")
    cfg = saved_config(dict(cfg_data) if isinstance(cfg_data, dict) else {}, str(path))
    envmap = None
    env_state = extra.get("envmap")
    if isinstance(env_state, dict) and "raw" in env_state:
        raw = env_state["raw"]
        envmap = EnvMap(raw.shape[1], raw.shape[-1]).to(device)
        envmap.load_state_dict(env_state)
        envmap.requires_grad_(False)
    g = ck.gaussians
    for p in g.params.values():
        p.requires_grad_(False)
    means = g.params["means"].detach().float()
    center = means.median(dim=0).values
    dist = (means - center).norm(dim=-1)
    radius = float(torch.quantile(dist[:100_000].cpu(), 0.9)) if dist.numel() else 1.0
    phase = _phase_of(extra, cfg, g, envmap is not None)
    return LoadedModel(
        gaussians=g,
        envmap=envmap,
        cfg=cfg,
        phase=phase,
        iteration=int(extra.get("iteration", 0)),
        mtime=mtime,
        center=[float(v) for v in center.cpu()],
        radius=max(radius, 1e-6),
        device=device,
        static=LoadedModel.precompute(g, phase.sh_degree),
        backend=frame_backend(cfg.backend, device),
    )


class ModelCache:
    """The latest model of one run folder, shared by every viewer of that job.

    ``get()`` re-reads the checkpoint when its mtime changed (cheap ``stat`` per call).
    A checkpoint that fails to load (e.g. a newer format) keeps the previous model.
    """

    def __init__(self, run_dir: Path, device: torch.device) -> None:
        self.path = Path(run_dir) / CHECKPOINT_NAME
        self.device = device
        self._model: LoadedModel | None = None
        self._lock = threading.Lock()
        self._envmap_png: tuple[float, bytes] | None = None

    def mtime(self) -> float | None:
        try:
            return self.path.stat().st_mtime
        except OSError:
            return None

    def get(self) -> LoadedModel | None:
        """The current model (reloaded if the file changed), or None before the first save."""
        mtime = self.mtime()
        with self._lock:
            if mtime is None:
                return self._model
            if self._model is None or self._model.mtime != mtime:
                try:
                    self._model = load_model(self.path, self.device)
                except Exception:
                    log.exception("viewer: cannot load %s; keeping the previous model", self.path)
            return self._model

    def envmap_png(self, height: int = 256) -> bytes | None:
        """The env map as an 8-bit sRGB lat-long PNG (2H × H), cached per checkpoint."""
        model = self.get()
        if model is None or model.envmap is None:
            return None
        with self._lock:
            if self._envmap_png is not None and self._envmap_png[0] == model.mtime:
                return self._envmap_png[1]
        with torch.no_grad():
            texels = model.envmap.texels().detach().float().cpu()
            img = cube_to_equirect(texels, height)
        data = _to_png(_to_uint8(img))
        with self._lock:
            self._envmap_png = (model.mtime, data)
        return data


def _to_uint8(linear: torch.Tensor) -> np.ndarray:
    srgb = linear_to_srgb(linear.detach().float().clamp(0, 1))
    return (srgb * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).cpu().numpy()


def _to_png(rgb: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb, "RGB").save(buf, "PNG")
    return buf.getvalue()


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    """Baseline JPEG of an (H, W, 3) uint8 image (libjpeg via Pillow)."""
    buf = io.BytesIO()
    Image.fromarray(rgb, "RGB").save(buf, "JPEG", quality=quality)
    return buf.getvalue()


def make_camera(spec: Any, scale: float) -> Camera:
    """The :class:`core.cameras.Camera` of a validated camera message at ``scale``.

    ``spec`` is a :class:`viewer_web.protocol.CameraMsg`; intrinsics given by the client
    are for its full width/height and are scaled with the image.
    """
    w, h = spec.width, spec.height
    if spec.intrinsics is not None:
        k = spec.intrinsics
        intr = Intrinsics(k.fx, k.fy, k.cx, k.cy, w, h)
    else:
        fy = 0.5 * h / math.tan(math.radians(spec.fov_y) / 2)
        intr = Intrinsics(fy, fy, w / 2.0, h / 2.0, w, h)
    if scale < 1.0:
        intr = intr.scaled(scale)
    if spec.w2c is not None:
        return Camera(intr, torch.tensor(spec.w2c, dtype=torch.float64).reshape(4, 4))
    return Camera.look_at(spec.eye, spec.target, spec.up, intr)


@torch.no_grad()
def render_channel(model: LoadedModel, camera: Camera, channel: str) -> np.ndarray:
    """One channel of one view as display-ready (H, W, 3) uint8 sRGB.

    Only what the channel needs is computed: shading (env map lookups) for ``final``
    and ``specular`` only; the depth colour map (turbo) only for ``depth``.
    """
    device = model.device
    bg = eval_background(model.cfg, device)
    phase = model.phase
    st = model.static
    colors = st.get("colors")
    if colors is None:
        colors = model.gaussians.colors(camera, phase.sh_degree)
    gb, _ = render_gbuffer_tensors(
        st["means"],
        None,
        None,
        st["opacities"],
        colors,
        st["normals"],
        st["w_r"],
        camera,
        covariances=st["covariances"],
        backend=model.backend,
        antialiased=phase.antialiased,
    )
    if channel in ("final", "specular"):
        shade = deferred_shade(
            gb, model.envmap, bg, enabled=phase.envmap and model.envmap is not None
        )
        img = shade.final if channel == "final" else shade.specular
    elif channel == "base":
        img = gb.base + (1 - gb.alpha[..., None]) * bg
    elif channel == "normal":
        n_world = gb.normal @ camera.R.to(gb.normal)
        n_world = n_world / n_world.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        rgb = (n_world * 0.5 + 0.5) * gb.alpha[..., None]  # already display-encoded
        return (rgb * 255.0 + 0.5).clamp(0, 255).to(torch.uint8).cpu().numpy()
    elif channel == "depth":
        depth, valid = geometry_depth(gb, phase.planar_depth)
        img = colormap(depth.cpu(), valid.cpu())
    elif channel == "w_r":
        img = gb.w_r[..., None].expand(-1, -1, 3)
    elif channel == "alpha":
        img = gb.alpha[..., None].expand(-1, -1, 3)
    else:
        raise ValueError(f"unknown channel {channel!r}")
    return _to_uint8(img)


def timed_frame(
    model: LoadedModel, spec: Any, scale: float, quality: int
) -> tuple[bytes, dict[str, Any]]:
    """Render and encode one frame; the JPEG and the header fields that describe it."""
    t0 = time.perf_counter()
    camera = make_camera(spec, scale)
    rgb = render_channel(model, camera, spec.channel)
    if model.device.type == "cuda":
        torch.cuda.synchronize(model.device)
    t1 = time.perf_counter()
    jpeg = encode_jpeg(rgb, quality)
    t2 = time.perf_counter()
    return jpeg, {
        "width": camera.width,
        "height": camera.height,
        "render_ms": round((t1 - t0) * 1000.0, 2),
        "encode_ms": round((t2 - t1) * 1000.0, 2),
        "iteration": model.iteration,
    }
