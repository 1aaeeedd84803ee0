"""COLMAP sparse models (text and binary): ``cameras``, ``images``, ``points3D``.

COLMAP already uses Glint's conventions: world-to-camera rotation (quaternion w, x,
y, z) and translation, OpenCV axes, pixel centres at +0.5. Only pinhole cameras are
accepted (distortion models with all-zero coefficients count as pinhole). Images
live in ``images/`` beside ``sparse/0`` (or ``sparse/``), optional object masks
(white = object) in ``masks/`` named like the images (``glint sfm`` writes them);
the 3D points become the scene's initial point cloud and set its bounds.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO

import numpy as np
import torch

from core.errors import SceneError
from core.scene.cameras import Intrinsics
from core.scene.formats.common import (
    IMAGE_EXTS,
    LoadOptions,
    ViewSpec,
    check_inside,
    finish,
    split_every,
    split_label,
    validate_rigid,
)
from core.scene.imageio import srgb_to_linear
from core.scene.views import Scene

# model id -> (name, number of parameters), as in COLMAP's src/colmap/sensor/models.h
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
MODEL_IDS = {name: i for i, (name, _) in CAMERA_MODELS.items()}
# pinhole part of each accepted model: (fx, fy, cx, cy) parameter indices; the rest is distortion
_PINHOLE_LAYOUT = {
    "SIMPLE_PINHOLE": (0, 0, 1, 2),
    "PINHOLE": (0, 1, 2, 3),
    "SIMPLE_RADIAL": (0, 0, 1, 2),
    "RADIAL": (0, 0, 1, 2),
    "OPENCV": (0, 1, 2, 3),
    "FULL_OPENCV": (0, 1, 2, 3),
}


@dataclass
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: list[float]


@dataclass
class ColmapImage:
    id: int
    qvec: np.ndarray  # (4,) w, x, y, z
    tvec: np.ndarray  # (3,)
    camera_id: int
    name: str


@dataclass
class ColmapModel:
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    xyz: np.ndarray  # (N, 3) float64
    rgb: np.ndarray  # (N, 3) uint8
    files: dict[str, Path]


def find_sparse_dir(root: Path) -> Path | None:
    """``sparse/0`` (COLMAP's mapper output) or ``sparse/`` holding a cameras file."""
    for d in (root / "sparse" / "0", root / "sparse"):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    return None


# -- quaternions -------------------------------------------------------------------


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (w, x, y, z) with w >= 0 (eigenvector method)."""
    Rxx, Ryx, Rzx, Rxy, Ryy, Rzy, Rxz, Ryz, Rzz = R.flat
    K = (
        np.array(
            [
                [Rxx - Ryy - Rzz, 0, 0, 0],
                [Ryx + Rxy, Ryy - Rxx - Rzz, 0, 0],
                [Rzx + Rxz, Rzy + Ryz, Rzz - Rxx - Ryy, 0],
                [Ryz - Rzy, Rzx - Rxz, Rxy - Ryx, Rxx + Ryy + Rzz],
            ]
        )
        / 3.0
    )
    vals, vecs = np.linalg.eigh(K)
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    return -q if q[0] < 0 else q


# -- text --------------------------------------------------------------------------


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of a COLMAP text file, comments dropped, blanks kept."""
    if not path.is_file():
        raise SceneError("file not found", file=path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"cannot read file: {e}", file=path) from e
    return [
        (i + 1, ln.strip())
        for i, ln in enumerate(text.splitlines())
        if not ln.lstrip().startswith("#")
    ]


def _parse(tokens: list[str], types: str, *, file: Path, line: int, what: str) -> list[Any]:
    if len(tokens) < len(types):
        raise SceneError(
            f"expected {what}, got {len(tokens)} values", file=file, field=f"line {line}"
        )
    try:
        return [
            int(t) if c == "i" else float(t) if c == "f" else t
            for c, t in zip(types, tokens, strict=False)
        ]
    except ValueError:
        raise SceneError(f"expected {what}: bad number", file=file, field=f"line {line}") from None


def read_cameras_text(path: Path) -> dict[int, ColmapCamera]:
    cams: dict[int, ColmapCamera] = {}
    for ln, text in _data_lines(path):
        if not text:
            continue
        tok = text.split()
        cid, model, w, h = _parse(
            tok, "isii", file=path, line=ln, what="CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"
        )
        if model not in MODEL_IDS:
            raise SceneError(f"unknown camera model {model!r}", file=path, field=f"line {ln}")
        n = CAMERA_MODELS[MODEL_IDS[model]][1]
        params = _parse(tok[4:], "f" * n, file=path, line=ln, what=f"{n} parameters for {model}")
        if len(tok) != 4 + n:
            raise SceneError(
                f"{model} takes {n} parameters, got {len(tok) - 4}", file=path, field=f"line {ln}"
            )
        cams[cid] = ColmapCamera(cid, model, w, h, params)
    return cams


def read_images_text(path: Path) -> dict[int, ColmapImage]:
    images: dict[int, ColmapImage] = {}
    lines = _data_lines(path)
    i = 0
    while i < len(lines):
        ln, text = lines[i]
        i += 1
        if not text:
            continue
        tok = text.split(maxsplit=9)
        what = "IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"
        vals = _parse(tok, "ifffffffis", file=path, line=ln, what=what)
        if len(tok) < 10:
            raise SceneError(f"expected {what}", file=path, field=f"line {ln}")
        images[vals[0]] = ColmapImage(
            vals[0], np.array(vals[1:5]), np.array(vals[5:8]), vals[8], tok[9]
        )
        i += 1  # the POINTS2D line that follows every image line (may be empty)
    return images


def read_points_text(path: Path) -> tuple[np.ndarray, np.ndarray]:
    xyz, rgb = [], []
    for ln, text in _data_lines(path):
        if not text:
            continue
        vals = _parse(
            text.split(), "ifffiii", file=path, line=ln, what="POINT3D_ID X Y Z R G B ERROR TRACK[]"
        )
        xyz.append(vals[1:4])
        rgb.append(vals[4:7])
    return np.array(xyz, dtype=np.float64).reshape(-1, 3), np.array(rgb, dtype=np.uint8).reshape(
        -1, 3
    )


# -- binary ------------------------------------------------------------------------


class _Reader:
    """Little-endian struct reads that turn a short file into a SceneError."""

    def __init__(self, path: Path, f: BinaryIO) -> None:
        self.path, self.f = path, f

    def read(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        data = self.f.read(size)
        if len(data) != size:
            raise SceneError(f"file ends early while reading {what} (truncated?)", file=self.path)
        return struct.unpack("<" + fmt, data)

    def skip(self, n: int, what: str) -> None:
        data = self.f.read(n)
        if len(data) != n:
            raise SceneError(f"file ends early while reading {what} (truncated?)", file=self.path)

    def cstring(self, what: str) -> str:
        out = bytearray()
        while (c := self.f.read(1)) != b"\0":
            if not c:
                raise SceneError(
                    f"file ends early while reading {what} (truncated?)", file=self.path
                )
            out += c
        return out.decode("utf-8", errors="replace")


def _open_binary(path: Path) -> BinaryIO:
    if not path.is_file():
        raise SceneError("file not found", file=path)
    return path.open("rb")


def read_cameras_binary(path: Path) -> dict[int, ColmapCamera]:
    cams: dict[int, ColmapCamera] = {}
    with _open_binary(path) as f:
        r = _Reader(path, f)
        (n,) = r.read("Q", "the camera count")
        for k in range(n):
            cid, mid, w, h = r.read("iiQQ", f"camera {k}")
            if mid not in CAMERA_MODELS:
                raise SceneError(f"unknown camera model id {mid}", file=path, field=f"camera {cid}")
            name, npar = CAMERA_MODELS[mid]
            params = list(r.read("d" * npar, f"camera {cid} parameters"))
            cams[cid] = ColmapCamera(cid, name, w, h, params)
    return cams


def read_images_binary(path: Path) -> dict[int, ColmapImage]:
    images: dict[int, ColmapImage] = {}
    with _open_binary(path) as f:
        r = _Reader(path, f)
        (n,) = r.read("Q", "the image count")
        for k in range(n):
            vals = r.read("idddddddi", f"image {k}")
            name = r.cstring(f"image {vals[0]} name")
            (npts,) = r.read("Q", f"image {vals[0]} point count")
            r.skip(24 * npts, f"image {vals[0]} points")
            images[vals[0]] = ColmapImage(
                vals[0], np.array(vals[1:5]), np.array(vals[5:8]), vals[8], name
            )
    return images


def read_points_binary(path: Path) -> tuple[np.ndarray, np.ndarray]:
    xyz, rgb = [], []
    with _open_binary(path) as f:
        r = _Reader(path, f)
        (n,) = r.read("Q", "the point count")
        for k in range(n):
            vals = r.read("QdddBBBd", f"point {k}")
            (track,) = r.read("Q", f"point {vals[0]} track length")
            r.skip(8 * track, f"point {vals[0]} track")
            xyz.append(vals[1:4])
            rgb.append(vals[4:7])
    return np.array(xyz, dtype=np.float64).reshape(-1, 3), np.array(rgb, dtype=np.uint8).reshape(
        -1, 3
    )


def read_model(sparse: Path) -> ColmapModel:
    """Read cameras/images/points3D, each from ``.bin`` when present, else ``.txt``."""

    def pick(stem: str) -> Path:
        b = sparse / f"{stem}.bin"
        return b if b.is_file() else sparse / f"{stem}.txt"

    files = {k: pick(k) for k in ("cameras", "images", "points3D")}
    binary = {k: p.suffix == ".bin" for k, p in files.items()}
    cams = (read_cameras_binary if binary["cameras"] else read_cameras_text)(files["cameras"])
    images = (read_images_binary if binary["images"] else read_images_text)(files["images"])
    if files["points3D"].is_file():
        xyz, rgb = (read_points_binary if binary["points3D"] else read_points_text)(
            files["points3D"]
        )
    else:
        xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return ColmapModel(cams, images, xyz, rgb, files)


# -- to Glint ----------------------------------------------------------------------


def camera_intrinsics(cam: ColmapCamera, *, file: Path) -> Intrinsics:
    """Pinhole intrinsics of a COLMAP camera, refusing real distortion."""
    field = f"camera {cam.id}"
    if cam.model not in _PINHOLE_LAYOUT:
        raise SceneError(
            f"camera model {cam.model} is not supported (only PINHOLE, SIMPLE_PINHOLE, or "
            "SIMPLE_RADIAL/RADIAL/OPENCV/FULL_OPENCV with zero distortion); "
            "run COLMAP's image_undistorter first",
            file=file,
            field=field,
        )
    p = np.asarray(cam.params, dtype=np.float64)
    if not np.isfinite(p).all():
        raise SceneError("camera parameters contain NaN or Inf", file=file, field=field)
    ifx, ify, icx, icy = _PINHOLE_LAYOUT[cam.model]
    dist = p[max(ifx, ify, icx, icy) + 1 :]
    if np.any(dist != 0):
        raise SceneError(
            f"{cam.model} camera has nonzero distortion {dist.tolist()}; undistort the "
            "images first (COLMAP image_undistorter) and use the PINHOLE model",
            file=file,
            field=field,
        )
    if p[ifx] <= 0 or p[ify] <= 0 or cam.width <= 0 or cam.height <= 0:
        raise SceneError("focal length and image size must be positive", file=file, field=field)
    return Intrinsics(
        float(p[ifx]), float(p[ify]), float(p[icx]), float(p[icy]), cam.width, cam.height
    )


def image_pose(img: ColmapImage, *, file: Path) -> np.ndarray:
    """World-to-camera 4x4 from a COLMAP image's quaternion and translation."""
    field = f"image {img.id} ({img.name})"
    q = np.asarray(img.qvec, dtype=np.float64)
    if not (np.isfinite(q).all() and np.isfinite(img.tvec).all()):
        raise SceneError("pose contains NaN or Inf", file=file, field=field)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-3:
        raise SceneError(
            f"quaternion is not unit length (|q| = {norm:.6g})", file=file, field=field
        )
    M = np.eye(4)
    M[:3, :3] = qvec_to_rotmat(q)
    M[:3, 3] = img.tvec
    return validate_rigid(M, file=file, field=field)


def find_mask(folder: Path, name: str) -> Path | None:
    """The mask of image ``name`` in ``folder``: same name, same stem with an image
    extension (``a.JPG`` → ``a.png``), or COLMAP's ``a.JPG.png``."""
    rel = PurePosixPath(name)
    cands = [folder / name, folder / f"{name}.png"]
    cands += [folder / rel.with_suffix(e) for ext in IMAGE_EXTS for e in (ext, ext.upper())]
    return next((c for c in cands if c.is_file()), None)


def _mask(root: Path, name: str) -> Path | None:
    """The image's mask when ``masks/`` exists (then every image needs one), else None."""
    folder = root / "masks"
    if not folder.is_dir():
        return None
    m = find_mask(folder, name)
    if m is None:
        raise SceneError(
            f"no mask for image {name} (masks/ must cover every image, named like it)",
            file=folder / PurePosixPath(name).with_suffix(".png"),
        )
    return m


def load(root: Path, opts: LoadOptions) -> Scene:
    """Load a COLMAP scene folder: ``sparse/0`` (or ``sparse``) + ``images/`` (+ ``masks/``)."""
    sparse = find_sparse_dir(root)
    if sparse is None:
        raise SceneError("no COLMAP model (sparse/0/cameras.{bin,txt})", file=root / "sparse")
    model = read_model(sparse)
    images_dir = root / "images"
    if not images_dir.is_dir():
        raise SceneError(
            "image folder not found (expected images/ beside sparse/)", file=images_dir
        )
    if not model.images:
        raise SceneError("the model has no registered images", file=model.files["images"])
    intr = {
        cid: camera_intrinsics(c, file=model.files["cameras"]) for cid, c in model.cameras.items()
    }
    specs = []
    for img in sorted(model.images.values(), key=lambda im: im.name):
        if img.camera_id not in intr:
            raise SceneError(
                f"camera_id {img.camera_id} is not in {model.files['cameras'].name}",
                file=model.files["images"],
                field=f"image {img.id} ({img.name})",
            )
        if not opts.allow_outside_root:
            check_inside(img.name, file=model.files["images"], field=f"image {img.id} name")
        path = images_dir / img.name
        if not path.is_file():
            raise SceneError(
                f"image '{img.name}' listed in {model.files['images']} not found", file=path
            )
        stem = PurePosixPath(img.name)
        name = str(stem.with_suffix("")) if stem.suffix.lower() in IMAGE_EXTS else img.name
        specs.append(
            ViewSpec(
                name=name,
                image=path,
                world_to_cam=image_pose(img, file=model.files["images"]),
                intrinsics=intr[img.camera_id],
                mask=_mask(root, img.name),
                meta={"colmap_image_id": img.id, "colmap_camera_id": img.camera_id},
            )
        )
    keep = np.isfinite(model.xyz).all(axis=1)
    points = colors = None
    meta: dict[str, Any] = {"warnings": [], "split": split_label(opts.test_every, "image by name")}
    if keep.any():
        points = torch.from_numpy(model.xyz[keep]).float()
        c = model.rgb[keep].astype(np.float32) / 255.0
        colors = torch.from_numpy(srgb_to_linear(c) if opts.linearize else c).float()
    else:
        meta["warnings"].append("COLMAP model has no 3D points; bounds come from the cameras")
    train, test = split_every(specs, opts.test_every)
    return finish(train, test, "colmap", root, opts, points=points, point_colors=colors, meta=meta)
