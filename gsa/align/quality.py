"""Ground-truth-free quality numbers of an alignment: forward and reverse inlier
fractions, the RMS residual of forward inliers and the agreement of the features of
spatial nearest neighbours (gsa.align.pipeline re-exports quality_metrics)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from gsa.align.nearest import query_workers
from gsa.render import steps
from gsa.sim3 import Sim3


def reverse_distances(transform: Sim3, target_points: np.ndarray, source_tree: cKDTree) -> np.ndarray:
    """Distance from each target point to the nearest mapped source point, in target units."""
    d, _ = source_tree.query(transform.inverse().apply(target_points), k=1, workers=query_workers(len(target_points)))
    return d * transform.scale


def reverse_inliers(transform: Sim3, target_points: np.ndarray, source_tree: cKDTree, threshold: float) -> float:
    return float(np.mean(reverse_distances(transform, target_points, source_tree) <= threshold))


def quality_metrics(
    transform: Sim3,
    src_pts: np.ndarray,
    dst_pts: np.ndarray,
    src_feat: np.ndarray,
    dst_feat: np.ndarray,
    threshold: float,
    src_tree: cKDTree,
    dst_tree: cKDTree,
    reverse_rows: np.ndarray | slice = slice(None),
) -> dict:
    """Ground-truth-free numbers a caller can judge a result by: the fractions of
    source (forward) and target (reverse) Gaussians with a partner within the
    inlier threshold, the RMS distance of forward inliers, and how well the
    features of spatial nearest neighbours agree."""
    steps.step()  # a due progress report (gsa.align.pair._Repeater)
    fwd_d, fwd_i = dst_tree.query(transform.apply(src_pts), k=1, workers=query_workers(len(src_pts)))
    steps.step()
    reverse = reverse_inliers(transform, dst_pts[reverse_rows], src_tree, threshold)
    inlier = fwd_d <= threshold
    forward = float(inlier.mean())
    feat_d = np.linalg.norm(np.asarray(src_feat, np.float64) - np.asarray(dst_feat, np.float64)[fwd_i], axis=1)
    return {
        "inlier_fraction": 0.5 * (forward + reverse),
        "inlier_fraction_forward": forward,
        "inlier_fraction_reverse": reverse,
        "rms_residual": float(np.sqrt(np.mean(fwd_d[inlier] ** 2))) if inlier.any() else float("inf"),
        "feature_distance_median": float(np.median(feat_d)),
        "feature_agreement": float(np.mean(feat_d <= 0.05)),
    }
