"""Score recovered cameras against known ones: similarity alignment and pose errors.

SfM recovers cameras up to a similarity (scale, rotation, translation), so before
comparing with truth the recovered camera centres are aligned to the true ones with
Umeyama's closed-form least-squares similarity; rotation errors are then the angle
of the residual rotation and centre errors are relative to the rig's extent (the
largest distance between two true camera centres), so they read the same for a
scene in millimetres or in metres.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """``x_truth = scale · R @ x_recovered + t``."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.scale * (np.asarray(x) @ self.R.T) + self.t


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """Least-squares similarity mapping points ``src`` (N, 3) onto ``dst`` (N, 3).

    Umeyama (1991): SVD of the cross-covariance, with the sign fix that keeps R a
    rotation (never a reflection). Needs three points that are not colinear.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"need matching (N>=3, 3) point sets, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = float((xs**2).sum() / len(src))
    if var_s <= 0:
        raise ValueError("source points are all the same point")
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(D) @ S) / var_s)
    return Similarity(scale, R, mu_d - scale * R @ mu_s)


def centers(w2c: np.ndarray) -> np.ndarray:
    """Camera centres (N, 3) of world-to-camera matrices (N, 4, 4)."""
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]
    return -np.einsum("nji,nj->ni", R, t)


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle (degrees) of rotation matrices (..., 3, 3)."""
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def rig_extent(c: np.ndarray) -> float:
    """Largest distance between two camera centres (the rig's diameter)."""
    d = np.linalg.norm(c[:, None, :] - c[None, :, :], axis=-1)
    return float(d.max())


@dataclass(frozen=True)
class PoseErrors:
    """Per-camera errors after alignment, in the order of ``names``."""

    names: list[str]
    rotation_deg: np.ndarray
    center_rel: np.ndarray  # centre error / rig extent
    similarity: Similarity
    extent: float

    def summary(self) -> dict[str, float]:
        return {
            "cameras": len(self.names),
            "rotation_deg_median": float(np.median(self.rotation_deg)),
            "rotation_deg_max": float(self.rotation_deg.max()),
            "center_rel_median": float(np.median(self.center_rel)),
            "center_rel_max": float(self.center_rel.max()),
            "scale": self.similarity.scale,
            "rig_extent": self.extent,
        }


def pose_errors(recovered: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray]) -> PoseErrors:
    """Align ``recovered`` world-to-camera 4x4s to ``truth`` (matched by name) and score them.

    Only names in both are compared; the caller reports how many were recovered.
    """
    names = sorted(set(recovered) & set(truth))
    if len(names) < 3:
        raise ValueError(f"need at least 3 cameras present in both sets, got {len(names)}")
    rec = np.stack([np.asarray(recovered[n], np.float64) for n in names])
    tru = np.stack([np.asarray(truth[n], np.float64) for n in names])
    c_rec, c_tru = centers(rec), centers(tru)
    sim = umeyama(c_rec, c_tru)
    # a recovered camera maps truth-frame points through R_c · Rᵀ; compare with the truth's
    R_aligned = rec[:, :3, :3] @ sim.R.T
    resid = R_aligned @ np.transpose(tru[:, :3, :3], (0, 2, 1))
    extent = rig_extent(c_tru)
    err_c = np.linalg.norm(sim.apply(c_rec) - c_tru, axis=-1) / (extent if extent > 0 else 1.0)
    return PoseErrors(names, rotation_angle_deg(resid), err_c, sim, extent)
