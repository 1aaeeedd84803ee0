"""Write a :class:`~core.scene.views.Scene` in every format ``load_scene`` reads.

Used for round-trip tests, by the API tests and by the demo. Metadata is written at
full float precision (JSON/text use Python's shortest round-trip repr, binaries
float64), so cameras survive a round trip exactly; images are PNG (8- or 16-bit,
sRGB-encoded), masks as alpha or as separate single-channel PNGs.
A scene a format cannot express (per-view intrinsics in Blender, an off-centre
principal point in LLFF) raises ``ValueError`` instead of writing a lossy file.
"""

from __future__ import annotations

import json
import math
import pickle
import struct
from pathlib import Path
from typing import Any

import numpy as np
import torch

from core.scene.cameras import Camera, Intrinsics
from core.scene.formats.colmap import MODEL_IDS, rotmat_to_qvec
from core.scene.formats.common import invert_rigid, w2c_to_opengl_c2w
from core.scene.imageio import linear_to_srgb, write_image
from core.scene.views import Scene, View


def flat_name(name: str) -> str:
    """A view name as one safe file-name component."""
    out = "".join(c if c.isalnum() or c in "-_." else "_" for c in name.replace("/", "_"))
    return out or "view"


def _unique_names(views: list[View], strip: str = "") -> list[str]:
    names, seen = [], set()
    for i, v in enumerate(views):
        base = v.name[len(strip) :] if strip and v.name.startswith(strip) else v.name
        n = flat_name(base or f"view_{i}")
        if n in seen:
            n = f"{n}_{i}"
        seen.add(n)
        names.append(n)
    return names


def _write_rgba(path: Path, view: View, bits: int, with_alpha: bool = True) -> Path:
    return write_image(path, view.image, alpha=view.mask if with_alpha else None, bits=bits)


def _write_mask(path: Path, mask: Any, bits: int) -> Path:
    return write_image(path, mask, encode_srgb=False, bits=bits)


def _shared_intrinsics(scene: Scene, fmt: str) -> Intrinsics:
    intr = {v.camera.intrinsics for v in scene.views}
    if len(intr) != 1:
        raise ValueError(f"{fmt} format holds one set of intrinsics; this scene has {len(intr)}")
    return intr.pop()


def _is_plain(i: Intrinsics) -> bool:
    """Square pixels and a centred principal point: camera_angle_x says it all."""
    return i.fx == i.fy and i.cx == i.width / 2 and i.cy == i.height / 2


def _json(path: Path, doc: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


def _c2w_list(cam: Camera) -> list[list[float]]:
    return w2c_to_opengl_c2w(cam.world_to_cam.numpy()).tolist()


# -- Blender / nerfstudio --------------------------------------------------------------


def write_blender(scene: Scene, out_dir: str | Path, *, bits: int = 8) -> Path:
    """NeRF-synthetic layout: ``transforms_{train,test}.json`` + ``{split}/{name}.png`` (RGBA)."""
    out = Path(out_dir)
    intr = _shared_intrinsics(scene, "Blender")
    for split, views in (("train", scene.train), ("test", scene.test)):
        frames = []
        for view, name in zip(views, _unique_names(views, strip=f"{split}/"), strict=True):
            _write_rgba(out / split / f"{name}.png", view, bits)
            frames.append(
                {"file_path": f"./{split}/{name}", "transform_matrix": _c2w_list(view.camera)}
            )
        doc: dict[str, Any] = {"camera_angle_x": 2.0 * math.atan(0.5 * intr.width / intr.fx)}
        if not _is_plain(intr):
            doc.update(
                fl_x=intr.fx, fl_y=intr.fy, cx=intr.cx, cy=intr.cy, w=intr.width, h=intr.height
            )
        doc["frames"] = frames
        _json(out / f"transforms_{split}.json", doc)
    return out


def write_nerfstudio(
    scene: Scene,
    out_dir: str | Path,
    *,
    bits: int = 8,
    mask_files: bool = False,
    camera_model: str = "PINHOLE",
) -> Path:
    """``transforms.json`` with per-frame intrinsics, ``images/``, and the split as
    ``train_filenames``/``test_filenames``; masks as alpha or as ``masks/`` + ``mask_path``."""
    out = Path(out_dir)
    frames, split = [], {"train": [], "test": []}
    views = scene.views
    for k, (view, name) in enumerate(zip(views, _unique_names(views), strict=True)):
        rel = f"images/{name}.png"
        _write_rgba(out / rel, view, bits, with_alpha=not mask_files)
        i = view.camera.intrinsics
        frame: dict[str, Any] = {
            "file_path": rel,
            "fl_x": i.fx,
            "fl_y": i.fy,
            "cx": i.cx,
            "cy": i.cy,
            "w": i.width,
            "h": i.height,
            "transform_matrix": _c2w_list(view.camera),
        }
        if mask_files and view.mask is not None:
            frame["mask_path"] = f"masks/{name}.png"
            _write_mask(out / frame["mask_path"], view.mask, bits)
        frames.append(frame)
        split["train" if k < len(scene.train) else "test"].append(rel)
    doc = {"camera_model": camera_model, "frames": frames}
    doc.update(train_filenames=split["train"], test_filenames=split["test"])
    _json(out / "transforms.json", doc)
    return out


# -- COLMAP --------------------------------------------------------------------------


def _colmap_tables(
    scene: Scene,
) -> tuple[dict[Intrinsics, int], list[tuple[int, np.ndarray, np.ndarray, int, str]]]:
    cams: dict[Intrinsics, int] = {}
    images = []
    names = _unique_names(scene.views)
    for k, (view, name) in enumerate(zip(scene.views, names, strict=True)):
        cid = cams.setdefault(view.camera.intrinsics, len(cams) + 1)
        w2c = view.camera.world_to_cam.numpy()
        images.append((k + 1, rotmat_to_qvec(w2c[:3, :3]), w2c[:3, 3].copy(), cid, f"{name}.png"))
    return cams, images


def _point_table(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    if scene.points is None:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    xyz = scene.points.detach().double().cpu().numpy()
    if scene.point_colors is None:
        rgb = np.full_like(xyz, 128, dtype=np.uint8)
    else:
        c = linear_to_srgb(scene.point_colors.detach().double().cpu().numpy())
        rgb = np.clip(np.round(c * 255), 0, 255).astype(np.uint8)
    return xyz, rgb


def write_colmap(scene: Scene, out_dir: str | Path, *, binary: bool = False, bits: int = 8) -> Path:
    """``sparse/0/{cameras,images,points3D}.{txt|bin}`` (PINHOLE) + ``images/`` (RGBA PNG)."""
    out = Path(out_dir)
    sparse = out / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    cams, images = _colmap_tables(scene)
    for view, (*_, name) in zip(scene.views, images, strict=True):
        _write_rgba(out / "images" / name, view, bits)
    xyz, rgb = _point_table(scene)
    if binary:
        _colmap_binary(sparse, cams, images, xyz, rgb)
    else:
        _colmap_text(sparse, cams, images, xyz, rgb)
    return out


def _colmap_text(sparse: Path, cams: dict, images: list, xyz: np.ndarray, rgb: np.ndarray) -> None:
    lines = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
    ]
    lines += [
        f"{cid} PINHOLE {i.width} {i.height} {i.fx!r} {i.fy!r} {i.cx!r} {i.cy!r}"
        for i, cid in cams.items()
    ]
    (sparse / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
    ]
    for iid, q, t, cid, name in images:
        vals = " ".join(repr(float(x)) for x in (*q, *t))
        lines += [f"{iid} {vals} {cid} {name}", ""]
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    lines = [
        "# 3D point list with one line of data per point:",
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]",
    ]
    lines += [
        f"{k + 1} {p[0]!r} {p[1]!r} {p[2]!r} {c[0]} {c[1]} {c[2]} 0.0"
        for k, (p, c) in enumerate(zip(xyz.tolist(), rgb.tolist(), strict=True))
    ]
    (sparse / "points3D.txt").write_text("\n".join(lines) + "\n")


def _colmap_binary(
    sparse: Path, cams: dict, images: list, xyz: np.ndarray, rgb: np.ndarray
) -> None:
    with (sparse / "cameras.bin").open("wb") as f:
        f.write(struct.pack("<Q", len(cams)))
        for i, cid in cams.items():
            f.write(
                struct.pack(
                    "<iiQQ4d", cid, MODEL_IDS["PINHOLE"], i.width, i.height, i.fx, i.fy, i.cx, i.cy
                )
            )
    with (sparse / "images.bin").open("wb") as f:
        f.write(struct.pack("<Q", len(images)))
        for iid, q, t, cid, name in images:
            f.write(struct.pack("<i7di", iid, *q, *t, cid))
            f.write(name.encode("utf-8") + b"\0")
            f.write(struct.pack("<Q", 0))
    with (sparse / "points3D.bin").open("wb") as f:
        f.write(struct.pack("<Q", len(xyz)))
        for k, (p, c) in enumerate(zip(xyz.tolist(), rgb.tolist(), strict=True)):
            f.write(struct.pack("<Q3d3BdQ", k + 1, *p, *c, 0.0, 0))


# -- LLFF ------------------------------------------------------------------------------


def write_llff(scene: Scene, out_dir: str | Path, *, bits: int = 8, hwf_scale: float = 1.0) -> Path:
    """``poses_bounds.npy`` + ``images/`` (+ ``masks/``), rows in sorted-name order.

    ``hwf_scale`` writes hwf for images that many times larger than the ones written,
    as real LLFF captures do (their hwf refers to the full-size photos).
    """
    out = Path(out_dir)
    intr = _shared_intrinsics(scene, "LLFF")
    if intr.fx != intr.fy or intr.cx != intr.width / 2 or intr.cy != intr.height / 2:
        raise ValueError(
            "LLFF holds one focal and a centred principal point; this scene has neither"
        )
    order = sorted(zip(_unique_names(scene.views), scene.views, strict=True), key=lambda p: p[0])
    rows = []
    for name, view in order:
        _write_rgba(out / "images" / f"{name}.png", view, bits, with_alpha=False)
        if view.mask is not None:
            _write_mask(out / "masks" / f"{name}.png", view.mask, bits)
        c2w = invert_rigid(view.camera.world_to_cam.numpy())
        R, t = c2w[:3, :3], c2w[:3, 3]
        hwf = np.array([intr.height, intr.width, intr.fx]) * hwf_scale
        # OpenCV columns (right, down, forward) -> LLFF (down, right, back)
        P = np.stack([R[:, 1], R[:, 0], -R[:, 2], t, hwf], 1)
        near, far = _near_far(view.camera, scene)
        rows.append(np.concatenate([P.reshape(-1), [near, far]]))
    np.save(out / "poses_bounds.npy", np.asarray(rows, dtype=np.float64))
    return out


def _near_far(cam: Camera, scene: Scene) -> tuple[float, float]:
    if "near" in cam.meta and "far" in cam.meta:
        return float(cam.meta["near"]), float(cam.meta["far"])
    d = float((cam.center - scene.center.to(cam.center)).norm())
    return max(d - scene.radius, 0.01 * d), d + scene.radius


# -- NeRO ------------------------------------------------------------------------------


def write_nero(
    scene: Scene, out_dir: str | Path, *, bits: int = 8, mask_files: bool = False
) -> Path:
    """``{k}.png`` + ``{k}-camera.pkl`` (pose 3x4 w2c, K) per view, ``{k}-mask.png`` optionally."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name, view in zip(_unique_names(scene.views), scene.views, strict=True):
        _write_rgba(out / f"{name}.png", view, bits, with_alpha=not mask_files)
        if mask_files and view.mask is not None:
            _write_mask(out / f"{name}-mask.png", view.mask, bits)
        pose = view.camera.world_to_cam.numpy()[:3, :4].copy()
        K = view.camera.K(dtype=torch.float64).numpy()
        with (out / f"{name}-camera.pkl").open("wb") as f:
            pickle.dump((pose, K), f)
    return out


WRITERS = {
    "blender": write_blender,
    "nerfstudio": write_nerfstudio,
    "colmap": write_colmap,
    "llff": write_llff,
    "nero": write_nero,
}


def write_scene(scene: Scene, out_dir: str | Path, format: str, **kwargs: Any) -> Path:
    """Write ``scene`` in ``format`` (one of :data:`WRITERS`)."""
    if format not in WRITERS:
        raise ValueError(f"unknown format {format!r}; expected one of {sorted(WRITERS)}")
    return WRITERS[format](scene, out_dir, **kwargs)
