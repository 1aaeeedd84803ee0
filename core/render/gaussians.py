"""Planar Gaussians: the trainable scene representation of PGSR-DR.

Parameters are stored unconstrained in one ``torch.nn.ParameterDict`` (one optimizer
group each, gsplat style); every constrained quantity is an accessor:

=================  ===========  ==========================================
key                shape        meaning
=================  ===========  ==========================================
``means``          (N, 3)       centres μ, world space
``log_scales``     (N, 3)       s = exp(log_scales)
``quats``          (N, 4)       rotation, (w, x, y, z), any length
``opacity_logits`` (N,)         α = sigmoid
``sh_dc``          (N, 1, 3)    SH degree 0
``sh_rest``        (N, 15, 3)   SH degrees 1..3 (degree-3 capacity)
``refl_logits``    (N,)         reflection strength w_r = sigmoid (Sect. 4.1)
=================  ===========  ==========================================

Covariance Σ = R S Sᵀ Rᵀ = R diag(s²) Rᵀ with R built from the unit quaternion exactly
as 3DGS's ``build_rotation``. Its principal axes are therefore the *columns* of R,
and the normal of Eq. 6 is the column k of R for k = argmin(s). The paper (after
NeuSG) writes "row R_i[k, :]": that is the same vector with R_i meaning the
world-to-local rotation Rᵀ (the glm/CUDA storage of 3DGS); PGSR's reference code
also takes ``build_rotation(q)[:, :, k]``, the column.

Densification and pruning go through :meth:`Gaussians.index_select` and
:meth:`Gaussians.cat`, which iterate over *all* keys, so any extra per-Gaussian
parameter is carried along without touching those code paths.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor, nn

from core.kernels.dispatch import cpu_float
from core.render.rotations import normalize_quats, quat_to_rotmat
from core.render.sh import MAX_SH_DEGREE, num_sh_bases, rgb_to_sh0, sh_to_rgb
from core.render.sh_compiled import sh_colors_compiled
from core.scene.cameras import Camera

# Trailing shape of every required parameter (leading dimension N).
PARAM_SHAPES: dict[str, tuple[int, ...]] = {
    "means": (3,),
    "log_scales": (3,),
    "quats": (4,),
    "opacity_logits": (),
    "sh_dc": (1, 3),
    "sh_rest": (num_sh_bases(MAX_SH_DEGREE) - 1, 3),
    "refl_logits": (),
}

# Per-Gaussian state kept with the parameters but never trained: what the views saw of
# each splat's sides (core.render.orientation). Carried through densification and
# checkpoints like a parameter; no optimizer, no gradient.
UNTRAINED_KEYS = ("seen_dir", "seen_count")

DEFAULT_INIT_OPACITY = 0.1
# Small, so base colour explains the images first and the environment map earns its
# weight where the scene is specular (3DGS-DR also starts near zero).
DEFAULT_INIT_REFL = 0.01
# Initial scale range relative to the scene radius: duplicated points (distance 0)
# and isolated outliers (huge neighbour distances) must not make degenerate or
# scene-sized splats.
SCALE_RANGE = (1e-4, 0.2)


def scalar_logit(p: float) -> float:
    if not 0.0 < p < 1.0:
        raise ValueError(f"probability must be in (0, 1) for a finite logit, got {p}")
    return math.log(p / (1.0 - p))


def _as_param(t: Tensor | nn.Parameter, requires_grad: bool = True) -> nn.Parameter:
    if isinstance(t, nn.Parameter):
        return t
    return nn.Parameter(t, requires_grad=requires_grad)


class Gaussians:
    """A set of N planar Gaussians with unconstrained parameters (see module docstring).

    ``sh_degree`` is the highest SH degree the model uses (the default for
    :meth:`colors`); storage always has degree-3 capacity.
    """

    def __init__(
        self, params: Mapping[str, Tensor] | nn.ParameterDict, sh_degree: int = MAX_SH_DEGREE
    ) -> None:
        if not 0 <= sh_degree <= MAX_SH_DEGREE:
            raise ValueError(f"sh_degree must be in 0..{MAX_SH_DEGREE}, got {sh_degree}")
        missing = [k for k in PARAM_SHAPES if k not in params]
        if missing:
            raise ValueError(f"Gaussians: missing parameter(s) {missing}")
        n = int(params["means"].shape[0])
        for key, t in params.items():
            if key in PARAM_SHAPES and tuple(t.shape) != (n, *PARAM_SHAPES[key]):
                raise ValueError(
                    f"Gaussians: parameter '{key}' has shape {tuple(t.shape)}, "
                    f"expected {(n, *PARAM_SHAPES[key])}"
                )
            if t.ndim == 0 or t.shape[0] != n:
                raise ValueError(f"Gaussians: parameter '{key}' does not have N={n} rows")
        if isinstance(params, nn.ParameterDict):
            self.params = params
        else:
            self.params = nn.ParameterDict(
                {k: _as_param(v, k not in UNTRAINED_KEYS) for k, v in params.items()}
            )
        self.sh_degree = int(sh_degree)

    # -- construction -----------------------------------------------------
    @staticmethod
    def from_points(
        points: Tensor | np.ndarray,
        colors: Tensor | np.ndarray | None = None,
        *,
        sh_degree: int = MAX_SH_DEGREE,
        init_opacity: float = DEFAULT_INIT_OPACITY,
        init_refl: float = DEFAULT_INIT_REFL,
        radius: float | None = None,
        device: torch.device | str = "cpu",
    ) -> Gaussians:
        """Isotropic Gaussians at ``points`` (N, 3) with ``colors`` (N, 3) in [0, 1].

        Scale = mean distance to the 3 nearest neighbours (3DGS uses the RMS of the
        same), clamped to ``SCALE_RANGE`` × ``radius`` (default: the cloud's radius
        about its centroid). uint8 colours are divided by 255; ``None`` means grey.
        """
        pts = np.asarray(torch.as_tensor(points).detach().cpu(), dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
            raise ValueError(f"points must be (N, 3) with N ≥ 1, got {pts.shape}")
        if not np.isfinite(pts).all():
            raise ValueError("points contain NaN or Inf")
        n = pts.shape[0]
        if colors is None:
            cols = np.full((n, 3), 0.5)
        else:
            c = torch.as_tensor(colors).detach().cpu()
            cols = c.numpy().astype(np.float64) / (255.0 if c.dtype == torch.uint8 else 1.0)
            if cols.shape != (n, 3):
                raise ValueError(f"colors must be ({n}, 3), got {cols.shape}")
            cols = np.nan_to_num(cols, nan=0.5).clip(0.0, 1.0)
        if radius is None:
            radius = float(np.linalg.norm(pts - pts.mean(0), axis=1).max())
        if not (math.isfinite(radius) and radius > 0):
            radius = 1.0

        lo, hi = SCALE_RANGE[0] * radius, SCALE_RANGE[1] * radius
        k = min(3, n - 1)
        if k == 0:
            scale = np.full(n, hi)
        else:
            dist, _ = cKDTree(pts).query(pts, k=k + 1)
            scale = dist[:, 1:].mean(axis=1)  # column 0 is the point itself
        scale = np.clip(scale, lo, hi)

        f32 = {"dtype": torch.float32, "device": device}
        quats = torch.zeros(n, 4, **f32)
        quats[:, 0] = 1.0
        params = {
            "means": torch.tensor(pts, **f32),
            "log_scales": torch.tensor(np.log(scale), **f32)[:, None].repeat(1, 3),
            "quats": quats,
            "opacity_logits": torch.full((n,), scalar_logit(init_opacity), **f32),
            "sh_dc": rgb_to_sh0(torch.tensor(cols, **f32))[:, None, :],
            "sh_rest": torch.zeros(n, *PARAM_SHAPES["sh_rest"], **f32),
            "refl_logits": torch.full((n,), scalar_logit(init_refl), **f32),
        }
        return Gaussians(params, sh_degree=sh_degree)

    @staticmethod
    def random(
        center: Tensor | list[float],
        radius: float,
        n: int,
        seed: int = 0,
        **kwargs: Any,
    ) -> Gaussians:
        """``n`` Gaussians uniform in the ball (``center``, ``radius``), random colours.

        Deterministic in ``seed``; ``kwargs`` go to :meth:`from_points`.
        """
        if n < 1:
            raise ValueError(f"n must be ≥ 1, got {n}")
        g = torch.Generator().manual_seed(int(seed))
        d = torch.randn(n, 3, generator=g, dtype=torch.float64)
        d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
        r = radius * torch.rand(n, 1, generator=g, dtype=torch.float64) ** (1.0 / 3.0)
        c = torch.as_tensor(center, dtype=torch.float64).reshape(1, 3)
        cols = torch.rand(n, 3, generator=g, dtype=torch.float64)
        return Gaussians.from_points(c + d * r, cols, radius=radius, **kwargs)

    @staticmethod
    def from_scene(scene: Any, n_random: int = 100_000, seed: int = 0, **kwargs: Any) -> Gaussians:
        """From the scene's sparse cloud when it has one, else random in its bounding ball."""
        pts = getattr(scene, "points", None)
        if pts is not None and len(pts) > 0:
            return Gaussians.from_points(
                pts, getattr(scene, "point_colors", None), radius=float(scene.radius), **kwargs
            )
        return Gaussians.random(scene.center, float(scene.radius), n_random, seed, **kwargs)

    # -- bookkeeping ------------------------------------------------------
    @property
    def num(self) -> int:
        return int(self.params["means"].shape[0])

    def __len__(self) -> int:
        return self.num

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    def keys(self) -> Iterator[str]:
        return iter(self.params.keys())

    def _map(self, fn: Any, requires_grad: bool | None = None) -> Gaussians:
        """New Gaussians whose parameters are fresh leaves ``fn(p.detach())``."""
        out = {}
        for k, p in self.params.items():
            rg = p.requires_grad if requires_grad is None else requires_grad
            out[k] = nn.Parameter(fn(p.detach()), requires_grad=rg)
        return Gaussians(out, sh_degree=self.sh_degree)

    def to(self, device: torch.device | str) -> Gaussians:
        """Like ``Tensor.to``: ``self`` if already on ``device``, else a moved copy.

        A copy has new Parameter objects, so build optimizers after moving.
        """
        device = torch.device(device)
        if device.type == "cuda" and device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        if all(p.device == device for p in self.params.values()):
            return self
        return self._map(lambda t: t.to(device))

    def clone(self) -> Gaussians:
        """An independent copy with new leaf Parameters (same ``requires_grad``)."""
        return self._map(lambda t: t.clone())

    def detach(self) -> Gaussians:
        """An independent, frozen snapshot (``requires_grad=False``): export, viewer."""
        return self._map(lambda t: t.clone(), requires_grad=False)

    def index_select(self, mask_or_idx: Tensor) -> Gaussians:
        """The Gaussians selected by a bool mask (N,) or long indices, every key carried."""
        idx = torch.as_tensor(mask_or_idx, device=self.device)
        if idx.dtype == torch.bool:
            if idx.shape != (self.num,):
                raise ValueError(f"mask must have shape ({self.num},), got {tuple(idx.shape)}")
            idx = idx.nonzero(as_tuple=True)[0]
        return self._map(lambda t: t[idx.long()])

    def cat(self, other: Gaussians) -> Gaussians:
        """This set followed by ``other`` (same keys); ``sh_degree`` is the larger."""
        if set(self.params.keys()) != set(other.params.keys()):
            raise ValueError(
                f"cannot concatenate Gaussians with keys {sorted(self.params.keys())} "
                f"and {sorted(other.params.keys())}"
            )
        out = {}
        for k, p in self.params.items():
            q = other.params[k].detach().to(p.device)
            out[k] = nn.Parameter(torch.cat([p.detach(), q]), requires_grad=p.requires_grad)
        return Gaussians(out, sh_degree=max(self.sh_degree, other.sh_degree))

    def state_dict(self) -> dict[str, Any]:
        """Plain tensors (detached) + ``sh_degree``: what a checkpoint stores."""
        return {
            "params": {k: p.detach() for k, p in self.params.items()},
            "sh_degree": self.sh_degree,
        }

    @staticmethod
    def from_state_dict(state: Mapping[str, Any], device: torch.device | str = "cpu") -> Gaussians:
        params = {k: torch.as_tensor(v).to(device) for k, v in state["params"].items()}
        return Gaussians(params, sh_degree=int(state.get("sh_degree", MAX_SH_DEGREE)))

    # -- constrained quantities ---------------------------------------------
    @property
    def means(self) -> Tensor:
        return self.params["means"]

    @property
    def scales(self) -> Tensor:
        return torch.exp(self.params["log_scales"])

    @property
    def opacities(self) -> Tensor:
        return torch.sigmoid(self.params["opacity_logits"])

    @property
    def w_r(self) -> Tensor:
        """Reflection strength w_r ∈ (0, 1) (Sect. 4.1), (N,)."""
        return torch.sigmoid(self.params["refl_logits"])

    @property
    def sh(self) -> Tensor:
        """All SH coefficients (N, 16, 3): DC first, then degrees 1..3."""
        return torch.cat([self.params["sh_dc"], self.params["sh_rest"]], dim=1)

    @property
    def unit_quats(self) -> Tensor:
        return normalize_quats(self.params["quats"])

    @property
    def rotations(self) -> Tensor:
        """(N, 3, 3); columns are the Gaussian's principal axes in world space."""
        return quat_to_rotmat(self.unit_quats)

    @property
    def covariances(self) -> Tensor:
        """Σ = R S² Rᵀ (N, 3, 3); singular by design once Eq. 7 flattens the Gaussians."""
        R = self.rotations
        return (R * self.scales.pow(2)[:, None, :]) @ R.transpose(-1, -2)

    def min_axis(self) -> Tensor:
        """Index k = argmin(s) of the shortest axis (N,), as in Eq. 6 and Eq. 7."""
        return self.params["log_scales"].argmin(dim=1)

    def normals(self, *, compiled: bool | None = None) -> Tensor:
        """Eq. 6: unit world-space axis of the smallest scale, (N, 3), unoriented.

        Column k of R (see the module docstring for the paper's "row" wording).
        Differentiable w.r.t. ``quats``; the choice of k is not (argmin).
        ``compiled``: one numba pass with its backward (core.render.normals_compiled;
        None: on the CPU), False: the torch ops below, the reference.
        """
        q, s = self.params["quats"], self.params["log_scales"]
        if compiled is None:
            compiled = cpu_float(q)
        if compiled:
            from core.render.normals_compiled import normals_compiled

            return normals_compiled(q, s)
        R = self.rotations
        k = self.min_axis()
        return R[torch.arange(self.num, device=R.device), :, k]

    def normals_toward(self, camera: Camera) -> Tensor:
        """Eq. 6 normals flipped to face ``camera``: n · (c − μ) ≥ 0."""
        n = self.normals()
        c = camera.center.to(dtype=n.dtype, device=n.device)
        facing = (n * (c - self.means.detach())).sum(dim=-1, keepdim=True) >= 0
        return torch.where(facing, n, -n)

    def colors(
        self, camera: Camera, degree: int | None = None, subset: Tensor | None = None
    ) -> Tensor:
        """View-dependent base colour (N, 3) for direction μ − camera centre, as 3DGS.

        ``degree`` defaults to ``sh_degree``; the result is ``eval + 0.5`` clamped at 0.
        ``subset`` (indices): the colours of those Gaussians only, in that order.
        """
        deg = self.sh_degree if degree is None else int(degree)

        def pick(t: Tensor) -> Tensor:
            return t if subset is None else t.index_select(0, subset)

        if self.device.type == "cpu":  # one compiled pass (core.render.sh_compiled): 4-5× faster
            p = self.params
            dc, rest, mu = (pick(p[k]) for k in ("sh_dc", "sh_rest", "means"))
            return sh_colors_compiled(deg, dc, rest, mu, camera.center)
        c = camera.center.to(dtype=self.means.dtype, device=self.device)
        return sh_to_rgb(deg, pick(self.sh), pick(self.means) - c)

    def __repr__(self) -> str:
        return f"Gaussians(num={self.num}, sh_degree={self.sh_degree}, device={self.device})"
