"""Render held-out test scenes nobody tuned on, in the dev data's exact layout.

The dev scenes in ``../shared/data`` are what every constant was judged on; this renders
new ones (a procedural shape, a material and a rotated light the dev set does not
combine) with the same renderer (Mitsuba 3, path tracer, max depth 12, 1024 spp, box
filter, hidden emitter), the same cameras (Fibonacci spheres at distance 4) and the
same files (``transforms_*.json``, RGBA PNGs, GT depth/normal EXRs, ``gt_points.ply``,
``gt_points_seen.npy``, ``gt_mesh.ply``, ``envmap.exr``, ``meta.json``), so ``glint
bench`` scores them exactly as it scores the dev scenes.

Mitsuba is a development tool here, not a dependency of the service:
``pip install mitsuba==3.9.1``; its LLVM variant needs a libLLVM with ``fminimum``
(Debian's ``libllvm19``: set ``DRJIT_LIBLLVM_PATH``), else ``--variant scalar_rgb``
(about 30× slower). ``python -m bench.render_unseen OUT --preset NAME --envmaps
../shared/data``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from core.evaluation.metrics import chamfer_distance
from core.scene.groundtruth import write_gt_points
from core.scene.imageio import read_image_array, write_image

CAMERA_ANGLE_X = 0.6911112070083618  # the dev data's (Blender's 50 mm on 36 mm)
RADIUS = 4.0
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))
TEST_PHASE = 4.476769531365456  # the dev data's azimuth offset of the test set
# The dev data's env-map frame: Mitsuba's envmap to_world that gives the lat-long
# convention u = 0.5 - atan2(y, x) / 2π, θ = acos(z) (README "Env map").
ENVMAP_TO_WORLD = [[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]
ENVMAP_SOURCES = {"courtyard": "teapot_gold", "forest": "spot_plastic", "studio": "sphere_mirror"}

PRESETS: dict[str, dict[str, Any]] = {
    # A closed tube whose three crossings hide and reflect each other: self-occlusion
    # and narrow gaps, in a metal the dev set has not got, under a turned light.
    "trefoil_aluminium": {
        "shape": "trefoil",
        "material": {"type": "roughconductor", "material": "Al", "alpha": 0.08},
        "envmap": "forest",
        "envmap_turn_deg": 150.0,
    },
    # A deep, open concavity (the vase's inside, seen from the upper views) and a waist,
    # in a coloured coated plastic under a light the dev plastics were not lit by.
    "vase_blue_plastic": {
        "shape": "vase",
        "material": {
            "type": "roughplastic",
            "diffuse_reflectance": {"type": "rgb", "value": [0.08, 0.2, 0.55]},
            "alpha": 0.12,
            "int_ior": 1.49,
        },
        "envmap": "courtyard",
        "envmap_turn_deg": 90.0,
    },
    # The same vase with a checker printed on (inside too): whether a well with texture
    # to match across views comes out hollow where the plain one is lidded.
    "vase_checker_plastic": {
        "shape": "vase",
        "material": {
            "type": "roughplastic",
            "checker": {"color0": [0.08, 0.2, 0.55], "color1": [0.85, 0.8, 0.7], "cells": [16, 8]},
            "alpha": 0.12,
            "int_ior": 1.49,
        },
        "envmap": "courtyard",
        "envmap_turn_deg": 90.0,
    },
    # A rougher metal than any dev scene (GGX α 0.25: the reflection nearly a blur).
    "trefoil_rough_gold": {
        "shape": "trefoil",
        "material": {"type": "roughconductor", "material": "Au", "alpha": 0.25},
        "envmap": "studio",
        "envmap_turn_deg": 60.0,
    },
}


# ---------------------------------------------------------------------------- shapes


def _closed_tube(curve: np.ndarray, radius: float, sides: int) -> trimesh.Trimesh:
    """A watertight tube around a closed polyline (N, 3), with rotation-minimising
    frames whose twist mismatch at the seam is spread evenly (no seam, no pinch)."""
    n = curve.shape[0]
    tangent = np.roll(curve, -1, 0) - np.roll(curve, 1, 0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.zeros_like(curve)
    seed = np.cross(tangent[0], [0.0, 0.0, 1.0])
    if np.linalg.norm(seed) < 1e-3:
        seed = np.cross(tangent[0], [1.0, 0.0, 0.0])
    normal[0] = seed / np.linalg.norm(seed)

    def transported(prev: np.ndarray, t: np.ndarray) -> np.ndarray:
        v = prev - np.dot(prev, t) * t
        return v / np.linalg.norm(v)

    for i in range(1, n):
        normal[i] = transported(normal[i - 1], tangent[i])
    closing = transported(normal[n - 1], tangent[0])  # once round, back at the start
    binormal0 = np.cross(tangent[0], normal[0])
    mismatch = math.atan2(np.dot(closing, binormal0), np.dot(closing, normal[0]))
    ring = np.linspace(0.0, 2.0 * math.pi, sides, endpoint=False)
    verts = np.empty((n, sides, 3))
    for i in range(n):
        binormal = np.cross(tangent[i], normal[i])
        turn = ring - mismatch * i / n
        verts[i] = curve[i] + radius * (
            np.cos(turn)[:, None] * normal[i] + np.sin(turn)[:, None] * binormal
        )
    idx = np.arange(n * sides).reshape(n, sides)
    a, b = idx, np.roll(idx, -1, 1)
    c, d = np.roll(idx, -1, 0), np.roll(np.roll(idx, -1, 0), -1, 1)
    faces = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)]).reshape(-1, 3)
    mesh = trimesh.Trimesh(verts.reshape(-1, 3), faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def trefoil(samples: int = 720, sides: int = 48) -> trimesh.Trimesh:
    """The trefoil knot (a curve about 5.5 across) as a tube of radius 0.42; where two
    strands pass closest, the gap between their surfaces is 0.37 (0.9 tube radii):
    narrow, open, and reflected in both."""
    t = np.linspace(0.0, 2.0 * math.pi, samples, endpoint=False)
    curve = np.stack(
        [np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t), -np.sin(3 * t)], 1
    )
    return _closed_tube(curve, radius=0.42, sides=sides)


def vase(segments: int = 160) -> trimesh.Trimesh:
    """A solid of revolution: a foot, a belly, a waist and a flared mouth, open at the
    top into a well half the object deep (a concavity only the upper views see into)."""
    z_out = np.linspace(-1.0, 1.0, 80)
    r_out = (
        0.55
        + 0.22 * np.sin(np.pi * (z_out + 1.0) / 1.4)
        - 0.1 * (z_out > 0.4) * np.sin(np.pi * (z_out - 0.4) / 0.6) ** 2
    )
    r_out = np.maximum(r_out, 0.3)
    wall = 0.07
    z_in = np.linspace(1.0, -0.2, 60)
    r_in = np.interp(z_in, z_out, r_out) - wall
    # (r, z) from the bottom centre, up the outside, over the rim, down the inside.
    profile = np.concatenate(
        [
            [[0.0, -1.0]],
            np.stack([r_out, z_out], 1),
            np.stack([r_in, z_in], 1),
            [[0.0, -0.2]],
        ]
    )
    mesh = trimesh.creation.revolve(profile, sections=segments)
    mesh.merge_vertices()
    if mesh.volume < 0:
        mesh.invert()
    return mesh


SHAPES = {"trefoil": trefoil, "vase": vase}


def normalize(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, np.ndarray]:
    """Centre on the minimum enclosing sphere, radius 1 (the dev data's frame)."""
    centre, radius = trimesh.nsphere.minimum_nsphere(mesh.vertices)
    m = np.eye(4)
    m[:3, :3] /= radius
    m[:3, 3] = -np.asarray(centre) / radius
    out = mesh.copy()
    out.apply_transform(m)
    return out, m


# --------------------------------------------------------------------------- cameras


def focal_px(size: int) -> float:
    """Focal length in pixels of a ``size``-pixel-wide dev-data image."""
    return 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)


def fibonacci_cameras(n: int, phase: float, *, upper: bool = False) -> list[np.ndarray]:
    """Camera-to-world (OpenGL: looks down −Z, +Y up) on the dev data's Fibonacci sphere;
    ``upper``: on its upper half only (z in (0, 1)), the layout of NeRF-synthetic /
    Shiny Blender and of a turntable photographed from above, where the underside is
    never seen."""
    out = []
    for i in range(n):
        z = 1.0 - (i + 0.5) / n if upper else 1.0 - (2 * i + 1) / n
        phi = i * GOLDEN_ANGLE + phase
        s = math.sqrt(max(0.0, 1.0 - z * z))
        eye = RADIUS * np.array([s * math.cos(phi), s * math.sin(phi), z])
        back = eye / np.linalg.norm(eye)  # camera +Z points away from the target
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, back, eye
        out.append(c2w)
    return out


def pixel_rays(c2w: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """World origins and unnormalised directions through pixel centres, z-component −1
    in the camera frame (so the hit distance along them is the z-depth)."""
    f = focal_px(size)
    j, i = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    cam = np.stack(
        [(i + 0.5 - size / 2) / f, -(j + 0.5 - size / 2) / f, -np.ones_like(i, float)], -1
    )
    dirs = cam.reshape(-1, 3) @ c2w[:3, :3].T
    return np.broadcast_to(c2w[:3, 3], dirs.shape), dirs


# ------------------------------------------------------------------------- rendering


def mitsuba_bsdf(mi: Any, material: dict) -> dict:
    """The preset's material as a Mitsuba BSDF dict: a ``checker`` (two linear RGB
    colours, cells along u and v) becomes its diffuse reflectance, read through the
    mesh's cylindrical UVs (:func:`cylindrical_uv`)."""
    out = {k: v for k, v in material.items() if k != "checker"}
    checker = material.get("checker")
    if checker is not None:
        out["diffuse_reflectance"] = {
            "type": "checkerboard",
            "color0": {"type": "rgb", "value": checker["color0"]},
            "color1": {"type": "rgb", "value": checker["color1"]},
            "to_uv": mi.ScalarTransform4f().scale([*checker["cells"], 1]),
        }
    return out


def cylindrical_uv(mesh: trimesh.Trimesh) -> np.ndarray:
    """(u, v) per vertex: the angle about +Z over 2π and the height; a texture seam
    where u wraps (one column of cells smeared, which no view is scored on)."""
    v = mesh.vertices
    return np.stack([(np.arctan2(v[:, 1], v[:, 0]) / (2 * math.pi)) % 1.0, (v[:, 2] + 1) / 2], 1)


class Renderer:
    """One Mitsuba scene (mesh, material, env map), rendered from any camera."""

    def __init__(self, mesh_path: Path, bsdf: dict, envmap_path: Path, scale: float, variant: str):
        import mitsuba as mi

        mi.set_variant(variant)
        self.mi = mi
        self.scene = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "path", "max_depth": 12, "hide_emitters": True},
                "emitter": {
                    "type": "envmap",
                    "filename": str(envmap_path),
                    "scale": scale,
                    "to_world": mi.ScalarTransform4f(ENVMAP_TO_WORLD),
                },
                "object": {
                    "type": "ply",
                    "filename": str(mesh_path),
                    "face_normals": False,
                    "bsdf": {"type": "twosided", "bsdf": mitsuba_bsdf(mi, bsdf)},
                },
            }
        )

    def image(
        self, c2w: np.ndarray, size: int, spp: int, seed: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Straight-alpha linear RGB (H, W, 3) and coverage alpha (H, W)."""
        mi = self.mi
        flip = np.diag([-1.0, 1.0, -1.0, 1.0])
        sensor = mi.load_dict(
            {
                "type": "perspective",
                "fov": math.degrees(CAMERA_ANGLE_X),
                "fov_axis": "x",
                "to_world": mi.ScalarTransform4f((c2w @ flip).tolist()),
                "sampler": {"type": "independent", "sample_count": spp, "seed": seed},
                "film": {
                    "type": "hdrfilm",
                    "width": size,
                    "height": size,
                    "pixel_format": "rgba",
                    "rfilter": {"type": "box"},
                },
            }
        )
        img = np.asarray(mi.render(self.scene, sensor=sensor, seed=seed), dtype=np.float64)
        alpha = np.clip(img[..., 3], 0.0, 1.0)
        rgb = np.where(alpha[..., None] > 0, img[..., :3] / np.maximum(alpha[..., None], 1e-12), 0)
        return rgb, alpha

    def first_hits(self, c2w: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
        """z-depth (H, W; 0 = none) and world shading normals facing the camera (H, W, 3)."""
        mi = self.mi
        o, d = pixel_rays(c2w, size)
        length = np.linalg.norm(d, axis=1)
        u = d / length[:, None]
        if mi.variant().startswith("scalar"):  # one ray at a time
            valid, t, n = np.zeros(len(u), bool), np.zeros(len(u)), np.zeros((len(u), 3))
            for k in range(len(u)):
                si = self.scene.ray_intersect(mi.Ray3f(o[k].tolist(), u[k].tolist()))
                valid[k], t[k], n[k] = bool(si.is_valid()), float(si.t), list(si.sh_frame.n)
        else:
            ray = mi.Ray3f(
                mi.Point3f(*[o[:, k].astype(np.float32) for k in range(3)]),
                mi.Vector3f(*[u[:, k].astype(np.float32) for k in range(3)]),
            )
            si = self.scene.ray_intersect(ray)
            valid = np.asarray(si.is_valid(), dtype=bool)
            t = np.asarray(si.t, dtype=np.float64)
            n = np.stack([np.asarray(c, dtype=np.float64) for c in si.sh_frame.n], 1)
        depth = np.where(valid, t / length, 0.0)
        n = np.where((np.sum(n * u, 1) > 0)[:, None], -n, n)
        n = np.where(valid[:, None], n, 0.0)
        return depth.reshape(size, size), n.reshape(size, size, 3)


# ----------------------------------------------------------------------------- files


def surface_points(mesh: trimesh.Trimesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n points uniform by area, with the interpolated vertex normals the renderer shades."""
    pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
    tri = mesh.triangles[face]
    bary = trimesh.triangles.points_to_barycentric(tri, pts)
    vn = mesh.vertex_normals[mesh.faces[face]]
    nrm = np.einsum("nk,nkd->nd", bary, vn)
    return pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


def chamfer_x100(a: np.ndarray, b: np.ndarray) -> float:
    """The evaluation's Chamfer distance ×10² (nothing dropped: both sets are surfaces)."""
    return float(chamfer_distance(a, b, max_radius=None)["cd_x100"])


def seen_by(
    points: np.ndarray, cams: list[np.ndarray], depths: list[np.ndarray], size: int
) -> np.ndarray:
    """Points within a pixel footprint of the first surface some train view sees."""
    f = focal_px(size)
    seen = np.zeros(len(points), bool)
    for c2w, depth in zip(cams, depths, strict=True):
        w2c = np.linalg.inv(c2w)
        p = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = -p[:, 2]
        i = np.floor(p[:, 0] / z * f + size / 2).astype(int)
        j = np.floor(-p[:, 1] / z * f + size / 2).astype(int)
        inside = (z > 0) & (i >= 0) & (i < size) & (j >= 0) & (j < size)
        d = np.zeros(len(points))
        d[inside] = depth[j[inside], i[inside]]
        seen |= inside & (d > 0) & (z <= d + 2.0 * z / f)
    return seen


def render_scene(
    out: Path, preset: str, envmaps: Path, *, size: int, n_train: int, n_test: int, spp: int,
    variant: str, seed: int = 0, upper: bool = False,
) -> dict[str, Any]:  # fmt: skip
    spec = dict(PRESETS[preset])
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    raw = SHAPES[spec["shape"]]()
    mesh, matrix = normalize(raw)
    if not mesh.is_watertight:
        raise RuntimeError(f"{preset}: the {spec['shape']} mesh is not watertight")
    mesh_path = out / "gt_mesh.ply"
    if "checker" in spec["material"]:
        mesh.visual = trimesh.visual.TextureVisuals(uv=cylindrical_uv(mesh))
    mesh.export(mesh_path)
    # The light: a dev env map turned about +Z by whole columns (exact, no resampling).
    src = envmaps / ENVMAP_SOURCES[spec["envmap"]] / "envmap.exr"
    env, _ = read_image_array(src)
    shift = round(spec["envmap_turn_deg"] / 360.0 * env.shape[1])
    write_image(out / "envmap.exr", np.roll(env[..., :3], shift, axis=1), encode_srgb=False)
    train_cams = fibonacci_cameras(n_train, 0.0, upper=upper)
    test_cams = fibonacci_cameras(n_test, TEST_PHASE, upper=upper)
    # Exposure as the dev data chose it (about 1 / the 90th percentile of the object's
    # linear values at scale 1), per pixel on its brightest channel so a coloured
    # object clips about as often as a grey one; from a cheap pass over every train
    # view (a sunlit diffuse side clips in the views that face it, most in none).
    probe = Renderer(mesh_path, spec["material"], out / "envmap.exr", 1.0, variant)
    vals = []
    for c2w in train_cams:
        rgb, a = probe.image(c2w, size, 16, seed)
        vals.append(rgb[a > 0.99].max(axis=-1))
    scale = float(f"{1.0 / np.percentile(np.concatenate(vals), 90):.3g}")
    renderer = Renderer(mesh_path, spec["material"], out / "envmap.exr", scale, variant)
    frames: dict[str, list] = {"train": [], "test": []}
    train_depths = []
    clipped = []
    for split, cams in (("train", train_cams), ("test", test_cams)):
        (out / split).mkdir(exist_ok=True)
        (out / f"{split}_gt").mkdir(exist_ok=True)
        for i, c2w in enumerate(cams):
            rgb, alpha = renderer.image(
                c2w, size, spp, seed * 100003 + i + (0 if split == "train" else 50000)
            )
            write_image(out / split / f"r_{i}.png", rgb, alpha)
            clipped.append(float((rgb[alpha > 0.99] >= 1.0).any(axis=-1).mean()))
            depth, normal = renderer.first_hits(c2w, size)
            write_image(
                out / f"{split}_gt" / f"r_{i}_depth.exr", depth[..., None], encode_srgb=False
            )
            write_image(
                out / f"{split}_gt" / f"r_{i}_normal.exr", normal, encode_srgb=False, bits=16
            )
            if split == "train":
                train_depths.append(depth)
            frames[split].append(
                {"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()}
            )
        (out / f"transforms_{split}.json").write_text(
            json.dumps({"camera_angle_x": CAMERA_ANGLE_X, "frames": frames[split]}, indent=1)
        )
    pts, nrm = surface_points(mesh, 200_000, seed)
    write_gt_points(out / "gt_points.ply", pts, nrm)
    np.save(out / "gt_points_seen.npy", seen_by(pts, train_cams, train_depths, size))
    floors = {
        "pred_200k_points": round(chamfer_x100(surface_points(mesh, 200_000, seed + 1)[0], pts), 3),
        "pred_1M_points": round(chamfer_x100(surface_points(mesh, 1_000_000, seed + 2)[0], pts), 3),
    }
    import mitsuba as mi

    meta = {
        "scene": out.name,
        "set": "unseen (bench/render_unseen.py; no constant was tuned on it)",
        "generator": "bench/render_unseen.py",
        "spec": {
            "name": out.name,
            "preset": preset,
            **spec,
            "resolution": [size, size],
            "n_train": n_train,
            "n_test": n_test,
            "cameras": "upper hemisphere" if upper else "sphere",
            "radius": RADIUS,
            "camera_angle_x": CAMERA_ANGLE_X,
            "spp": spp,
            "max_depth": 12,
            "seed": seed,
        },
        "mitsuba_version": mi.__version__,
        "mitsuba_variant": variant,
        "mesh": {
            "source": f"procedural ({spec['shape']}, bench/render_unseen.py)",
            "vertices": len(mesh.vertices),
            "faces": len(mesh.faces),
            "watertight": bool(mesh.is_watertight),
        },
        "normalization": {"matrix_4x4": matrix.tolist()},
        "material": {"mitsuba_bsdf": {"type": "twosided", "bsdf": spec["material"]}},
        "envmap": {
            "name": spec["envmap"],
            "source": str(src),
            "turned_about_z_deg": shift / env.shape[1] * 360.0,
            "scale": scale,
            "mitsuba_to_world": ENVMAP_TO_WORLD,
            "visible_in_background": False,
        },
        "image": {"width": size, "height": size, "object_pixels_clipping": float(np.mean(clipped))},
        "gt": {"chamfer_sampling_floor_x100": floors},
        "render_seconds": round(time.time() - t0, 1),
    }
    (out / "meta.json").write_text(json.dumps(meta, indent=1))
    return meta


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("out", type=Path, help="scene folder to write (its name is the scene's)")
    ap.add_argument("--preset", choices=sorted(PRESETS), required=True)
    ap.add_argument("--envmaps", type=Path, default=Path("../shared/data"),
                    help="the dev data folder whose scenes hold the three env maps")  # fmt: skip
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--n-train", type=int, default=64)
    ap.add_argument("--n-test", type=int, default=16)
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--upper", action="store_true",
        help="cameras on the upper half of the Fibonacci sphere only (the underside unseen)",
    )  # fmt: skip
    a = ap.parse_args(argv)
    meta = render_scene(
        a.out, a.preset, a.envmaps, size=a.size, n_train=a.n_train, n_test=a.n_test,
        spp=a.spp, variant=a.variant, seed=a.seed, upper=a.upper,
    )  # fmt: skip
    print(
        json.dumps(
            {k: meta[k] for k in ("scene", "envmap", "gt", "image", "render_seconds")}, indent=1
        )
    )


if __name__ == "__main__":
    main()
