"""Similarity transforms and the hybrid closed-form absolute-orientation solver.

A Sim3 maps x -> s R x + t. `solve_sim3` is the paper's App. G: Kabsch–Umeyama
rotation and translation with Horn's symmetric scale
s = sqrt(Σ‖y−ȳ‖² / Σ‖x−x̄‖²) (the appendix omits the root; the authors' code has it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsa.errors import GSAError
from gsa.geometry import quat_to_rotation, rotation_to_quat


class DegenerateCorrespondencesError(GSAError, ValueError):
    """Too few, collinear or coincident correspondences to fix a similarity."""


@dataclass(frozen=True)
class Sim3:
    scale: float
    rotation: np.ndarray  # (3, 3) float64, det +1
    translation: np.ndarray  # (3,) float64

    def __post_init__(self) -> None:
        object.__setattr__(self, "scale", float(self.scale))
        object.__setattr__(self, "rotation", np.asarray(self.rotation, np.float64).reshape(3, 3))
        object.__setattr__(self, "translation", np.asarray(self.translation, np.float64).reshape(3))
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"Sim3 scale must be a positive finite number, got {self.scale}")

    @classmethod
    def identity(cls) -> Sim3:
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, m: np.ndarray) -> Sim3:
        """From a 4x4 matrix [[sR, t], [0, 1]]; fails if sR is not a scaled rotation."""
        m = np.asarray(m, np.float64)
        if m.shape != (4, 4):
            raise ValueError(f"expected a 4x4 matrix, got {m.shape}")
        a = m[:3, :3]
        det = np.linalg.det(a)
        if det <= 0:
            raise ValueError("the 3x3 block has a non-positive determinant (a reflection or singular)")
        s = det ** (1.0 / 3.0)
        r = a / s
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-5):
            raise ValueError("the 3x3 block is not a uniformly scaled rotation")
        u, _, vt = np.linalg.svd(r)
        return cls(s, u @ vt, m[:3, 3])

    @classmethod
    def from_quaternion(cls, scale: float, quat_wxyz, translation) -> Sim3:
        return cls(scale, quat_to_rotation(np.asarray(quat_wxyz, np.float64)), translation)

    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def quaternion(self) -> np.ndarray:
        """Rotation as a unit w,x,y,z quaternion with w >= 0."""
        return rotation_to_quat(self.rotation)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) -> (..., 3) float64."""
        p = np.asarray(points, np.float64)
        return self.scale * (p @ self.rotation.T) + self.translation

    def compose(self, other: Sim3) -> Sim3:
        """self ∘ other: apply `other` first, then `self`."""
        return Sim3(
            self.scale * other.scale,
            self.rotation @ other.rotation,
            self.scale * self.rotation @ other.translation + self.translation,
        )

    __matmul__ = compose

    def inverse(self) -> Sim3:
        r_inv = self.rotation.T
        return Sim3(1.0 / self.scale, r_inv, -(r_inv @ self.translation) / self.scale)

    def to_dict(self) -> dict:
        return {
            "transform": self.matrix().tolist(),
            "scale": self.scale,
            "rotation": self.rotation.tolist(),
            "quaternion": self.quaternion().tolist(),
            "translation": self.translation.tolist(),
        }


def solve_sim3(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> Sim3:
    """Closed-form T minimising Σ w_i ‖s R x_i + t − y_i‖² (rotation, translation)
    with Horn's symmetric scale.

    src, dst: (N, 3) corresponding points; weights: optional (N,) non-negative.
    Raises DegenerateCorrespondencesError for < 3 points, all-zero weights or
    collinear / coincident points, where the rotation is not determined.
    """
    x = np.asarray(src, np.float64)
    y = np.asarray(dst, np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"expected two (N, 3) arrays of equal shape, got {x.shape} and {y.shape}")
    if len(x) < 3:
        raise DegenerateCorrespondencesError(f"need at least 3 correspondences, got {len(x)}")
    w = np.ones(len(x)) if weights is None else np.asarray(weights, np.float64).reshape(-1)
    if len(w) != len(x) or (w < 0).any() or not np.isfinite(w).all():
        raise ValueError("weights must be finite, non-negative and one per correspondence")
    total = w.sum()
    if total <= 0 or (w > 0).sum() < 3:
        raise DegenerateCorrespondencesError("fewer than 3 correspondences carry weight")
    w = w / total
    x_bar = w @ x
    y_bar = w @ y
    xc = x - x_bar
    yc = y - y_bar
    var_x = w @ np.einsum("ij,ij->i", xc, xc)
    var_y = w @ np.einsum("ij,ij->i", yc, yc)
    h = (xc * w[:, None]).T @ yc  # Σ w (x−x̄)(y−ȳ)ᵀ
    u, sv, vt = np.linalg.svd(h)
    # Rank < 2 (collinear or coincident points) leaves a free rotation about an axis.
    scale_ref = max(sv[0], 1e-300)
    if var_x <= 0 or var_y <= 0 or sv[1] <= 1e-9 * scale_ref:
        raise DegenerateCorrespondencesError(
            "correspondences are collinear or coincident; the rotation is not determined"
        )
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    s = float(np.sqrt(var_y / var_x))
    t = y_bar - s * rot @ x_bar
    return Sim3(s, rot, t)
