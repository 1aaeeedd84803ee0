"""Analytic test scenes, ray traced in torch: no rasteriser, no data files needed.

A sphere (radius 0.6) or a cube at the origin with a smooth diffuse albedo, shaded
with the same model Glint fits (Eq. 9): ``C = base + w_r · E(reflect(d, n))`` with an
analytic environment ``E`` (sky/ground gradient, world +Z up, plus two bright lobes).
``kind`` picks the material: ``diffuse`` (w_r = 0), ``mirror`` (base = 0, w_r = 1) or
``glossy`` (both). Cameras sit on a Fibonacci sphere looking at the origin, like the
dev scenes. Alpha is exact pixel coverage from regular supersampling, RGB straight.
Tests, the demo and the planner use these scenes, so they must stay fast.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from core.scene.cameras import Camera, Intrinsics
from core.scene.views import Scene, View

EnvFn = Callable[[Tensor], Tensor]
KINDS = ("diffuse", "mirror", "glossy")
SHAPES = ("sphere", "box")
SPHERE_RADIUS = 0.6
BOX_HALF = 0.4
NERF_FOV_X = 0.6911112070083618  # NeRF-synthetic's camera_angle_x (50 mm lens)
_GOLDEN = math.pi * (3.0 - math.sqrt(5.0))
_KEY_LIGHT = (0.4, 0.3, 0.85)  # direction of the diffuse key light (view independent)
# (base scale, w_r) of each material
_MATERIALS = {"diffuse": (1.0, 0.0), "mirror": (0.0, 1.0), "glossy": (0.6, 0.35)}


def _unit(v: tuple[float, float, float], like: Tensor) -> Tensor:
    t = torch.tensor(v, dtype=like.dtype, device=like.device)
    return t / t.norm()


def default_env(dirs: Tensor) -> Tensor:
    """Linear RGB radiance for unit world directions (..., 3); +Z is up.

    A smooth sky/ground gradient (blue zenith, pale horizon, brown ground) plus a
    warm sun-like lobe and a cooler fill lobe, so mirror reflections carry clear,
    direction-dependent structure.
    """
    z = dirs[..., 2:3]
    zenith = dirs.new_tensor([0.25, 0.45, 0.85])
    horizon = dirs.new_tensor([0.85, 0.85, 0.80])
    ground = dirs.new_tensor([0.30, 0.22, 0.15])
    up = horizon + (zenith - horizon) * z.clamp(0, 1).sqrt()
    t = torch.sigmoid(z * 12.0)  # smooth horizon line
    base = up * t + (ground + (horizon - ground) * (z + 1).clamp(0, 1) ** 4) * (1 - t)
    sun = torch.exp(40.0 * ((dirs * _unit((1.0, 0.5, 0.8), dirs)).sum(-1, keepdim=True) - 1.0))
    fill = torch.exp(12.0 * ((dirs * _unit((-0.7, -0.6, 0.3), dirs)).sum(-1, keepdim=True) - 1.0))
    return (
        base
        + 3.0 * sun * dirs.new_tensor([1.0, 0.9, 0.7])
        + 0.8 * fill * dirs.new_tensor([0.6, 0.8, 1.0])
    )


def albedo(points: Tensor, seed: int = 0) -> Tensor:
    """Smooth diffuse albedo (..., 3) in [0.05, 0.95] as a function of the surface point."""
    g = torch.Generator().manual_seed(seed)
    phase = (torch.rand(3, 3, generator=g) * 2 * math.pi).to(points)
    x, y, z = points[..., 0:1], points[..., 1:2], points[..., 2:3]
    a = (
        0.5
        + 0.25 * torch.sin(4.0 * x + phase[0]) * torch.cos(3.0 * y + phase[1])
        + 0.15 * torch.sin(5.0 * z + phase[2])
    )
    return a.clamp(0.05, 0.95)


def irradiance(normals: Tensor) -> Tensor:
    """View-independent diffuse shading factor (..., 1): ambient + one key light."""
    return 0.35 + 0.65 * (normals * _unit(_KEY_LIGHT, normals)).sum(-1, keepdim=True).clamp_min(0.0)


def intersect(origin: Tensor, dirs: Tensor, shape: str) -> tuple[Tensor, Tensor, Tensor]:
    """First hit of rays ``origin + t·dirs`` with the shape: (hit mask, t, unit normal)."""
    if shape == "sphere":
        b = dirs @ origin
        c = origin @ origin - SPHERE_RADIUS**2
        disc = b * b - c
        hit = disc >= 0
        t = -b - disc.clamp_min(0).sqrt()
        hit = hit & (t > 0)
        n = origin + t[..., None] * dirs
        return hit, t, n / n.norm(dim=-1, keepdim=True)
    if shape == "box":
        safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
        t1 = (-BOX_HALF - origin) / safe
        t2 = (BOX_HALF - origin) / safe
        tmin = torch.minimum(t1, t2).amax(-1)
        tmax = torch.maximum(t1, t2).amin(-1)
        hit = (tmax >= tmin) & (tmin > 0)
        p = origin + tmin[..., None] * dirs
        axis = p.abs().argmax(-1, keepdim=True)
        n = torch.zeros_like(p).scatter(-1, axis, torch.sign(p.gather(-1, axis)))
        return hit, tmin, n
    raise ValueError(f"unknown shape {shape!r}; expected one of {SHAPES}")


def shade(
    points: Tensor, normals: Tensor, dirs: Tensor, kind: str, env: EnvFn, seed: int = 0
) -> Tensor:
    """Eq. 9 with an analytic environment: base(p, n) + w_r · env(reflect(d, n))."""
    if kind not in _MATERIALS:
        raise ValueError(f"unknown kind {kind!r}; expected one of {KINDS}")
    k_base, w_r = _MATERIALS[kind]
    color = torch.zeros_like(points)
    if k_base > 0:
        color = color + k_base * albedo(points, seed) * irradiance(normals)
    if w_r > 0:
        refl = dirs - 2.0 * (dirs * normals).sum(-1, keepdim=True) * normals
        color = color + w_r * env(F.normalize(refl, dim=-1))
    return color


@dataclass
class SyntheticRender:
    """One rendered view: RGB (H, W, 3) straight alpha, clipped to [0, 1]; alpha (H, W)
    coverage; z-depth (H, W) and world normals (H, W, 3) at pixel centres, 0 = no surface."""

    rgb: Tensor
    alpha: Tensor
    depth: Tensor
    normal: Tensor


def render_synthetic_view(
    camera: Camera,
    *,
    shape: str = "sphere",
    kind: str = "glossy",
    env: EnvFn | None = None,
    samples: int = 4,
    seed: int = 0,
) -> SyntheticRender:
    """Ray trace one view with ``samples``² regular subsamples per pixel.

    The subsamples are the pixel centres of the camera scaled by ``samples`` (pixel
    edges map to pixel edges), so box-averaging them gives exact-coverage alpha.
    """
    env = env or default_env
    s = max(1, int(samples))
    fine = camera.scaled(s) if s > 1 else camera
    o, d = fine.world_rays(torch.float32)
    hit, t, n = intersect(o, d, shape)
    p = o + t[..., None] * d
    col = torch.where(hit[..., None], shade(p, n, d, kind, env, seed), 0.0)
    cov = hit.float()

    def pool(x: Tensor) -> Tensor:
        return F.avg_pool2d(x.permute(2, 0, 1)[None], s)[0].permute(1, 2, 0) if s > 1 else x

    alpha = pool(cov[..., None])[..., 0]
    pre = pool(col)
    rgb = torch.where(alpha[..., None] > 0, pre / alpha.clamp_min(1e-8)[..., None], 0.0).clamp(
        0.0, 1.0
    )
    # centre-sample depth and normals (no anti-aliasing), like the dev scenes' GT maps
    oc, dc = camera.world_rays(torch.float32)
    hc, tc, nc = intersect(oc, dc, shape)
    z = tc * (dc @ camera.forward.float())  # ray distance -> z-depth
    depth = torch.where(hc, z, 0.0)
    normal = torch.where(hc[..., None], nc, 0.0)
    return SyntheticRender(rgb.contiguous(), alpha.contiguous(), depth, normal)


def fibonacci_cameras(
    n: int,
    *,
    distance: float = 3.0,
    size: int = 64,
    fov_x: float = NERF_FOV_X,
    azimuth: float = 0.0,
    prefix: str = "r",
) -> list[Camera]:
    """``n`` cameras on a Fibonacci sphere (z_i = 1 − (2i+1)/n) looking at the origin, +Z up."""
    intr = Intrinsics.from_fov_x(fov_x, size, size)
    cams = []
    for i in range(n):
        z = 1.0 - (2 * i + 1) / n
        r = math.sqrt(max(0.0, 1.0 - z * z))
        phi = azimuth + i * _GOLDEN
        eye = [distance * r * math.cos(phi), distance * r * math.sin(phi), distance * z]
        cams.append(
            Camera.look_at(eye, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], intr, name=f"{prefix}_{i}")
        )
    return cams


def surface_points(shape: str = "sphere", n: int = 10000, seed: int = 0) -> tuple[Tensor, Tensor]:
    """Uniform-by-area points (n, 3) and outward normals on the shape (ground truth)."""
    g = torch.Generator().manual_seed(seed)
    if shape == "sphere":
        nrm = F.normalize(torch.randn(n, 3, generator=g), dim=-1)
        return nrm * SPHERE_RADIUS, nrm
    if shape == "box":
        face = torch.randint(0, 6, (n,), generator=g)
        uv = (torch.rand(n, 2, generator=g) * 2 - 1) * BOX_HALF
        axis, sign = face // 2, (face % 2) * 2 - 1.0
        p = torch.zeros(n, 3)
        nrm = torch.zeros(n, 3)
        others = torch.stack([(axis + 1) % 3, (axis + 2) % 3], dim=-1)
        p.scatter_(1, others, uv)
        p.scatter_(1, axis[:, None], (sign * BOX_HALF)[:, None])
        nrm.scatter_(1, axis[:, None], sign[:, None])
        return p, nrm
    raise ValueError(f"unknown shape {shape!r}; expected one of {SHAPES}")


def make_scene(
    shape: str = "sphere",
    kind: str = "glossy",
    *,
    n_train: int = 16,
    n_test: int = 4,
    size: int = 64,
    seed: int = 0,
    env: EnvFn | None = None,
    samples: int = 4,
    distance: float = 3.0,
    fov_x: float = NERF_FOV_X,
) -> Scene:
    """An analytic scene: ``n_train`` + ``n_test`` RGBA views of ``shape`` in ``kind``.

    ``seed`` rotates both Fibonacci sets in azimuth and sets the albedo pattern. The
    test set is a second Fibonacci set shifted by half a golden angle, so no test
    view repeats a train view. ``center``/``radius`` are the true bounding sphere.
    """
    if shape not in SHAPES:
        raise ValueError(f"unknown shape {shape!r}; expected one of {SHAPES}")
    if kind not in KINDS:
        raise ValueError(f"unknown kind {kind!r}; expected one of {KINDS}")
    az = float(torch.rand(1, generator=torch.Generator().manual_seed(seed))) * 2 * math.pi
    rigs = {
        "train": fibonacci_cameras(
            n_train, distance=distance, size=size, fov_x=fov_x, azimuth=az, prefix="train/r"
        ),
        "test": fibonacci_cameras(
            n_test,
            distance=distance,
            size=size,
            fov_x=fov_x,
            azimuth=az + 0.5 * _GOLDEN,
            prefix="test/r",
        ),
    }
    views: dict[str, list[View]] = {}
    for split, cams in rigs.items():
        views[split] = []
        for cam in cams:
            r = render_synthetic_view(
                cam, shape=shape, kind=kind, env=env, samples=samples, seed=seed
            )
            views[split].append(View(camera=cam, image=r.rgb, mask=r.alpha, name=cam.name))
    radius = SPHERE_RADIUS if shape == "sphere" else BOX_HALF * math.sqrt(3.0)
    base, w_r = _MATERIALS[kind]
    return Scene(
        train=views["train"],
        test=views["test"],
        center=torch.zeros(3, dtype=torch.float64),
        radius=radius,
        format="synthetic",
        meta={
            "warnings": [],
            "synthetic": {
                "shape": shape,
                "kind": kind,
                "base_scale": base,
                "w_r": w_r,
                "seed": seed,
            },
        },
    )


def make_sphere_scene(
    kind: str = "glossy",
    n_train: int = 16,
    n_test: int = 4,
    size: int = 64,
    seed: int = 0,
    env: EnvFn | None = None,
    samples: int = 4,
) -> Scene:
    """The radius-0.6 sphere scene (see :func:`make_scene`)."""
    return make_scene(
        "sphere",
        kind,
        n_train=n_train,
        n_test=n_test,
        size=size,
        seed=seed,
        env=env,
        samples=samples,
    )


def write_synthetic_scene(
    out_dir: str | Path,
    shape: str = "sphere",
    kind: str = "glossy",
    *,
    ground_truth: bool = False,
    gt_points: int = 20_000,
    **kwargs,
) -> Path:
    """Render a scene and write it in Blender (NeRF-synthetic) format; returns the folder.

    ``ground_truth``: also write what the dev scenes ship for scoring geometry and
    lighting, ``{split}_gt/{name}_depth.exr`` and ``_normal.exr`` (exact, at pixel
    centres), ``gt_points.ply`` (``gt_points`` points uniform on the surface, with
    normals) and ``envmap.exr`` (the environment as a lat-long map).
    """
    from core.scene.formats.writers import write_blender

    scene = make_scene(shape, kind, **kwargs)
    out = write_blender(scene, out_dir)
    if ground_truth:
        write_ground_truth(scene, out, shape, n_points=gt_points)
        write_envmap_latlong(kwargs.get("env") or default_env, out / "envmap.exr")
    return out


def write_envmap_latlong(env: EnvFn, path: str | Path, height: int = 128) -> Path:
    """The environment as a float lat-long EXR (2H × H) in the dev data's convention:
    for d = (x, y, z), column = (0.5 − atan2(y, x)/2π)·W − 0.5, row = acos(z)/π·(H − 1)."""
    from core.scene.imageio import write_image

    width = 2 * height
    theta = torch.arange(height, dtype=torch.float64) / (height - 1) * math.pi
    phi = (0.5 - (torch.arange(width, dtype=torch.float64) + 0.5) / width) * 2 * math.pi
    tt, pp = torch.meshgrid(theta, phi, indexing="ij")
    dirs = torch.stack([tt.sin() * pp.cos(), tt.sin() * pp.sin(), tt.cos()], dim=-1)
    return write_image(path, env(dirs.float()), encode_srgb=False)


def write_ground_truth(scene: Scene, out_dir: str | Path, shape: str, n_points: int) -> None:
    """GT depth/normal maps of every view and GT surface points, in the dev-scene layout."""
    from core.scene.formats.writers import _unique_names
    from core.scene.groundtruth import write_gt_points
    from core.scene.imageio import write_image

    out = Path(out_dir)
    for split, views in (("train", scene.train), ("test", scene.test)):
        for view, name in zip(views, _unique_names(views, strip=f"{split}/"), strict=True):
            r = render_synthetic_view(view.camera, shape=shape, samples=1)
            folder = out / f"{split}_gt"
            folder.mkdir(parents=True, exist_ok=True)
            depth = r.depth[..., None].expand(-1, -1, 3)
            write_image(folder / f"{name}_depth.exr", depth, encode_srgb=False)
            write_image(folder / f"{name}_normal.exr", r.normal, encode_srgb=False)
    pts, nrm = surface_points(shape, n_points)
    write_gt_points(out / "gt_points.ply", pts.numpy(), nrm.numpy())
