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

from core.config import TrainConfig
from core.model.channels import CHANNELS
from core.model.frame import to_display
from core.model.trained import CHECKPOINT_NAME, TrainedModel
from core.render.envmap_io import cube_to_equirect
from core.render.raster import fallback_backend
from core.scene.cameras import Camera, Intrinsics
from core.stages import stage

log = logging.getLogger("glint.viewer")

__all__ = ["CHANNELS", "LoadedModel", "ModelCache", "encode_jpeg", "render_channel"]


def default_device() -> torch.device:
    """The GPU when there is one: viewers must not compete with training for the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


@dataclass
class LoadedModel:
    """One checkpoint as the viewer holds it: the frozen model, the file's mtime (to
    notice a newer checkpoint) and where a client first looks."""

    model: TrainedModel
    mtime: float
    center: list[float]
    radius: float

    @property
    def iteration(self) -> int:
        return self.model.iteration

    @property
    def device(self) -> torch.device:
        return self.model.device

    @property
    def backend(self) -> str:
        return self.model.backend

    @property
    def cfg(self) -> TrainConfig:
        """The run's config as recorded."""
        return self.model.config

    def summary(self) -> dict[str, Any]:
        """The ``model`` message: what the client shows and frames its first view with."""
        return {**self.model.summary(), "center": self.center, "radius": self.radius}


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
    """Read a checkpoint for viewing (weights only; raises CheckpointError if unreadable).

    A backend this device lacks gives way to one it has (see ``frame_backend``)."""
    mtime = path.stat().st_mtime
    notes: list[str] = []
    model = TrainedModel.open(path, device=str(device), notes=notes).freeze()
    for note in notes:
        log.info("viewer: %s", note)
    center, radius = model.framing()
    return LoadedModel(model=model, mtime=mtime, center=center, radius=radius)


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
        loaded = self.get()
        if loaded is None or loaded.model.envmap is None:
            return None
        with self._lock:
            if self._envmap_png is not None and self._envmap_png[0] == loaded.mtime:
                return self._envmap_png[1]
        with torch.no_grad():
            texels = loaded.model.envmap.texels().detach().float().cpu()
            img = cube_to_equirect(texels, height)
        data = _to_png(to_display(img))
        with self._lock:
            self._envmap_png = (loaded.mtime, data)
        return data


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
    """The :class:`core.scene.cameras.Camera` of a validated camera message at ``scale``.

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
def render_channel(loaded: LoadedModel, camera: Camera, channel: str) -> np.ndarray:
    """One channel of one view as display-ready (H, W, 3) uint8 sRGB.

    Only what the channel needs is computed (see ``TrainedModel.render``)."""
    image = loaded.model.render(camera, (channel,)).image(channel)
    with stage("display"):
        return to_display(image)


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
    with stage("jpeg"):
        jpeg = encode_jpeg(rgb, quality)
    t2 = time.perf_counter()
    return jpeg, {
        "width": camera.width,
        "height": camera.height,
        "render_ms": round((t1 - t0) * 1000.0, 2),
        "encode_ms": round((t2 - t1) * 1000.0, 2),
        "iteration": model.iteration,
    }
