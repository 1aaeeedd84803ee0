"""A glTF 2.0 binary (.glb) of one textured mesh with a metallic-roughness material.

Written by hand (the format is small): trimesh's exporter has no tangents and no
control over texture packing, and the asset must pass Khronos' glTF-Validator.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# glTF is +Y up; Glint's world (the dev data's, Blender's) is +Z up: glTF = R · world.
GLTF_FROM_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_FLOAT, _UNSIGNED_INT = 5126, 5125
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP = 9729, 9987, 33071


@dataclass
class GlbTextures:
    """PNG bytes of the material's textures (occlusion shares the ORM image's R)."""

    base_color: bytes
    orm: bytes  # R occlusion (or 255), G roughness, B metallic
    normal: bytes | None = None
    has_occlusion: bool = False


@dataclass
class GlbMesh:
    """Vertex data in Glint's world frame; converted to glTF's on writing."""

    positions: np.ndarray  # (V, 3)
    normals: np.ndarray  # (V, 3)
    tangents: np.ndarray  # (V, 4)
    uvs: np.ndarray  # (V, 2), glTF convention (v down)
    faces: np.ndarray  # (F, 3)
    extras: dict[str, Any] = field(default_factory=dict)


class _Bin:
    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict[str, Any]] = []

    def add(self, payload: bytes, target: int | None = None) -> int:
        while len(self.data) % 4:
            self.data.append(0)
        view: dict[str, Any] = {
            "buffer": 0,
            "byteOffset": len(self.data),
            "byteLength": len(payload),
        }
        if target is not None:
            view["target"] = target
        self.data.extend(payload)
        self.views.append(view)
        return len(self.views) - 1


def write_glb(path: str | Path, mesh: GlbMesh, textures: GlbTextures, name: str = "glint") -> int:
    """Write the .glb (atomically: temp file, then rename); returns its size in bytes."""
    rot = GLTF_FROM_WORLD
    pos = (mesh.positions.astype(np.float64) @ rot.T).astype(np.float32)
    nrm = (mesh.normals.astype(np.float64) @ rot.T).astype(np.float32)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    tan_xyz = (mesh.tangents[:, :3].astype(np.float64) @ rot.T).astype(np.float32)
    tan_xyz /= np.maximum(np.linalg.norm(tan_xyz, axis=1, keepdims=True), 1e-12)
    tan = np.concatenate([tan_xyz, np.where(mesh.tangents[:, 3:4] < 0, -1.0, 1.0)], 1)
    tan = tan.astype(np.float32)
    uv = mesh.uvs.astype(np.float32)
    idx = mesh.faces.astype(np.uint32)
    b = _Bin()
    accessors: list[dict[str, Any]] = []

    def accessor(
        arr: np.ndarray, kind: str, target: int, ctype: int = _FLOAT, bounds: bool = False
    ) -> int:
        view = b.add(np.ascontiguousarray(arr).tobytes(), target)
        acc: dict[str, Any] = {
            "bufferView": view,
            "componentType": ctype,
            "count": int(arr.shape[0]),
            "type": kind,
        }
        if bounds:
            acc["min"] = [float(v) for v in arr.min(0)]
            acc["max"] = [float(v) for v in arr.max(0)]
        accessors.append(acc)
        return len(accessors) - 1

    attributes = {
        "POSITION": accessor(pos, "VEC3", _ARRAY_BUFFER, bounds=True),
        "NORMAL": accessor(nrm, "VEC3", _ARRAY_BUFFER),
        "TANGENT": accessor(tan, "VEC4", _ARRAY_BUFFER),
        "TEXCOORD_0": accessor(uv, "VEC2", _ARRAY_BUFFER),
    }
    indices = accessor(idx.reshape(-1), "SCALAR", _ELEMENT_ARRAY_BUFFER, _UNSIGNED_INT)
    accessors[indices]["min"] = [int(idx.min())] if idx.size else [0]
    accessors[indices]["max"] = [int(idx.max())] if idx.size else [0]
    images: list[dict[str, Any]] = []
    texture_defs: list[dict[str, Any]] = []
    for png in (textures.base_color, textures.orm, textures.normal):
        if png is None:
            continue
        images.append({"bufferView": b.add(png), "mimeType": "image/png"})
        texture_defs.append({"sampler": 0, "source": len(images) - 1})
    material: dict[str, Any] = {
        "name": f"{name}_material",
        "pbrMetallicRoughness": {
            "baseColorTexture": {"index": 0},
            "metallicRoughnessTexture": {"index": 1},
            "metallicFactor": 1.0,
            "roughnessFactor": 1.0,
        },
    }
    if textures.normal is not None:
        material["normalTexture"] = {"index": 2}
    if textures.has_occlusion:
        material["occlusionTexture"] = {"index": 1}
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "Glint (core.asset)"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [
            {
                "name": name,
                "primitives": [{"attributes": attributes, "indices": indices, "material": 0}],
            }
        ],
        "materials": [material],
        "samplers": [
            {
                "magFilter": _LINEAR,
                "minFilter": _LINEAR_MIPMAP_LINEAR,
                "wrapS": _CLAMP,
                "wrapT": _CLAMP,
            }
        ],
        "textures": texture_defs,
        "images": images,
        "accessors": accessors,
        "bufferViews": b.views,
        "buffers": [{"byteLength": 0}],
    }
    if mesh.extras:
        doc["extras"] = mesh.extras
    while len(b.data) % 4:
        b.data.append(0)
    doc["buffers"][0]["byteLength"] = len(b.data)
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + len(b.data)
    blob = b"".join(
        [
            struct.pack("<4sII", b"glTF", 2, total),
            struct.pack("<I4s", len(js), b"JSON"),
            js,
            struct.pack("<I4s", len(b.data), b"BIN\x00"),
            bytes(b.data),
        ]
    )
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(blob)
    tmp.replace(path)
    return total
