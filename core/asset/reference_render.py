"""A plain renderer of an exported asset under its environment, as a glTF viewer would
shade it (without Fresnel): the check that the file says what the model learned.

It reads the .glb back (the writer's own accessors, not the in-memory arrays), casts one
ray per pixel at the mesh (Embree), decodes the textures and the tangent-space normal
map, and shades C = (1 − m)·c·Irr(n)·AO + lerp(0.04, c, m)·E_ρ(reflect(v, n)) with
Glint's env map lookup (the same mip chain and ρ → level mapping the model renders
with). Where this render and Glint's disagree, the bake or the mapping is at fault;
where Blender disagrees with this one, glTF's shading (Fresnel, GGX sampling) is.
"""

from __future__ import annotations

import io
import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from core.asset.glb import GLTF_FROM_WORLD
from core.asset.material import DIELECTRIC_F0, irradiance, irradiance_sh
from core.render.envmap_mips import mip_sizes, roughness_to_lod, sample_cube_lod
from core.scene.cameras import Camera
from core.scene.imageio import srgb_to_linear

_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
_DTYPES = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}


@dataclass
class GlbAsset:
    """A .glb's mesh (glTF frame) and its decoded textures (linear floats, H × W × 3)."""

    positions: np.ndarray
    normals: np.ndarray
    tangents: np.ndarray
    uvs: np.ndarray
    faces: np.ndarray
    base_color: np.ndarray
    orm: np.ndarray
    normal_map: np.ndarray | None


def read_glb(path: str | Path) -> GlbAsset:
    """Parse a .glb as written by :func:`core.asset.glb.write_glb`."""
    data = Path(path).read_bytes()
    magic, _, _ = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF":
        raise ValueError(f"{path}: not a glb file")
    jlen, _ = struct.unpack_from("<I4s", data, 12)
    doc = json.loads(data[20 : 20 + jlen])
    blen, _ = struct.unpack_from("<I4s", data, 20 + jlen)
    bin_ = data[28 + jlen : 28 + jlen + blen]

    def view_bytes(i: int) -> bytes:
        v = doc["bufferViews"][i]
        return bin_[v.get("byteOffset", 0) : v.get("byteOffset", 0) + v["byteLength"]]

    def accessor(i: int) -> np.ndarray:
        a = doc["accessors"][i]
        arr = np.frombuffer(view_bytes(a["bufferView"]), dtype=_DTYPES[a["componentType"]])
        return arr.reshape(a["count"], _COMPONENTS[a["type"]])

    def image(tex: int, srgb: bool) -> np.ndarray:
        from PIL import Image

        src = doc["textures"][tex]["source"]
        raw = view_bytes(doc["images"][src]["bufferView"])
        x = np.asarray(Image.open(io.BytesIO(raw)).convert("RGB"), dtype=np.float32) / 255.0
        return np.asarray(srgb_to_linear(x)) if srgb else x

    prim = doc["meshes"][0]["primitives"][0]
    att = prim["attributes"]
    mat = doc["materials"][prim["material"]]
    pbr = mat["pbrMetallicRoughness"]
    normal_tex = mat.get("normalTexture")
    return GlbAsset(
        positions=accessor(att["POSITION"]).astype(np.float64),
        normals=accessor(att["NORMAL"]).astype(np.float64),
        tangents=accessor(att["TANGENT"]).astype(np.float64),
        uvs=accessor(att["TEXCOORD_0"]).astype(np.float64),
        faces=accessor(prim["indices"]).reshape(-1, 3).astype(np.int64),
        base_color=image(pbr["baseColorTexture"]["index"], srgb=True),
        orm=image(pbr["metallicRoughnessTexture"]["index"], srgb=False),
        normal_map=None if normal_tex is None else image(normal_tex["index"], srgb=False),
    )


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample (H, W, C) at glTF UVs (N, 2) with clamp-to-edge, texel centres at +0.5."""
    h, w = img.shape[:2]
    x = np.clip(uv[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip(uv[:, 1] * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def render_asset(
    asset: GlbAsset,
    env_texels: torch.Tensor | None,
    camera: Camera,
    background: np.ndarray,
    *,
    use_normal_map: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Linear RGB (H, W, 3) of the asset seen by ``camera`` over ``background``, and the
    hit mask (H, W). ``env_texels`` None: the base colour alone (a diffuse asset)."""
    rot = GLTF_FROM_WORLD
    world_pos = asset.positions @ rot  # rows: R^T p
    mesh = trimesh.Trimesh(world_pos, asset.faces, process=False)
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    origin, dirs = camera.world_rays(torch.float64)
    h, w = dirs.shape[:2]
    d = dirs.reshape(-1, 3).numpy()
    o = np.broadcast_to(origin.numpy(), d.shape)
    loc, ray_idx, tri = RayMeshIntersector(mesh).intersects_location(o, d, multiple_hits=False)
    img = np.broadcast_to(background.astype(np.float64), (h * w, 3)).copy()
    hit = np.zeros(h * w, dtype=bool)
    if len(ray_idx) == 0:
        return img.reshape(h, w, 3), hit.reshape(h, w)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], loc)
    f = asset.faces[tri]

    def interp(attr: np.ndarray) -> np.ndarray:
        return np.einsum("nk,nkc->nc", bary, attr[f])

    uv = interp(asset.uvs)
    n_geo = _unit(interp(asset.normals) @ rot)
    c = _bilinear(asset.base_color, uv)
    orm = _bilinear(asset.orm, uv)
    ao, rough, metal = orm[:, 0], orm[:, 1], orm[:, 2]
    n = n_geo
    if use_normal_map and asset.normal_map is not None:
        t = _unit(interp(asset.tangents[:, :3]) @ rot)
        t = _unit(t - n_geo * np.sum(t * n_geo, 1, keepdims=True))
        sign = np.where(asset.tangents[f[:, 0], 3] < 0, -1.0, 1.0)[:, None]
        b = np.cross(n_geo, t) * sign
        ts = _bilinear(asset.normal_map, uv) * 2.0 - 1.0
        n = _unit(ts[:, :1] * t + ts[:, 1:2] * b + ts[:, 2:3] * n_geo)
    if env_texels is None:
        color = c
    else:
        env = env_texels.detach().double().cpu()
        irr = irradiance(irradiance_sh(env), n)
        v = d[ray_idx]
        r = v - 2.0 * np.sum(v * n, 1, keepdims=True) * n
        levels = len(mip_sizes(env.shape[1]))
        lod = roughness_to_lod(torch.from_numpy(rough), env.shape[1], levels)
        spec = sample_cube_lod(env, torch.from_numpy(r), lod).numpy()
        f0 = DIELECTRIC_F0 * (1 - metal)[:, None] + metal[:, None] * c
        color = (1 - metal)[:, None] * c * irr * ao[:, None] + f0 * spec
    img[ray_idx] = color
    hit[ray_idx] = True
    return img.reshape(h, w, 3), hit.reshape(h, w)
