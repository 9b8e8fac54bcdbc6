"""Accuracy against a known transform (RRE, scale error, ATE) and GT-free quality."""

from __future__ import annotations

import numpy as np

from gsa.geometry import rotation_distance_deg
from gsa.sim3 import Sim3


def rre_deg(r_est: np.ndarray, r_gt: np.ndarray) -> float:
    """Relative rotation error: the angle of R_est R_gtᵀ in degrees (safe near 0 and 180)."""
    return rotation_distance_deg(r_est, r_gt)


def scale_error_pct(s_est: float, s_gt: float) -> float:
    """|s_est − s_gt| / s_gt in percent (paper App. C)."""
    return float(abs(s_est - s_gt) / s_gt * 100.0)


def ate(est: Sim3, gt: Sim3, source_points: np.ndarray, target_points: np.ndarray) -> tuple[float, float]:
    """RMS distance between the source mapped by `est` and by `gt` (target units),
    and the same divided by the target's bounding-box diagonal."""
    d = est.apply(source_points) - gt.apply(source_points)
    rms = float(np.sqrt(np.mean(np.einsum("ij,ij->i", d, d))))
    t = np.asarray(target_points, np.float64)
    diag = float(np.linalg.norm(t.max(axis=0) - t.min(axis=0)))
    return rms, rms / diag if diag > 0 else float("inf")


def accuracy(est: Sim3, gt: Sim3, source_points: np.ndarray, target_points: np.ndarray) -> dict:
    ate_abs, ate_norm = ate(est, gt, source_points, target_points)
    return {
        "rre_deg": rre_deg(est.rotation, gt.rotation),
        "scale_error_pct": scale_error_pct(est.scale, gt.scale),
        "ate": ate_abs,
        "ate_normalized": ate_norm,
    }
