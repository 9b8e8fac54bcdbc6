"""The Sim(3) between two reconstructions from their photos' shared texture (gsa.recon.anchors).

Each source descriptor is matched to the most alike target descriptor, kept when it is clearly
more alike than the best one of any other target point (Lowe's ratio test, taken across points:
a point's own views would otherwise fail it). The matched 3D points vote for point pairs; a
RANSAC over 3-pair similarity fits finds the pose most of them agree with, and the inliers' least
squares fit (gsa.sim3.solve_sim3) is the answer. Where the two models show different objects or
share no texture, few pairs agree and the match is refused: align() then runs as it does for
any two models.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsa.geometry import rotation_angle
from gsa.recon.anchors import PhotoAnchors
from gsa.sim3 import DegenerateCorrespondencesError, Sim3, solve_sim3

RATIO = 0.8  # Lowe's test
# Brute-force matching costs |source| × |target| distances (20k a side: ~8 s on 2 cores): past
# this many descriptors a side (a large scene's SfM) each point keeps one, then a seeded random
# share of the points is matched; a registration needs hundreds of pairs, not all.
MAX_DESCRIPTORS = 20_000
RANSAC_SAMPLES = 2000
# An inlier lies within this share of the target points' median distance from their median.
INLIER_RADIUS = 0.02
# Accepted only with this many distinct point pairs agreeing, and this share of all matched
# pairs: pairs of unrelated texture agree by chance with a handful at most (the minimal 3 and a
# few more), a shared object with hundreds (docs/benchmarks.md, "Photo matches").
MIN_INLIERS = 20
MIN_INLIER_SHARE = 0.2
# The inliers must span a plane at least: collinear points leave a rotation free.
MIN_SPREAD = 0.05
# A second pose that this share of the best one's pairs agree with (among the rest) makes the
# photos ambiguous: the pose is left to the geometry.
RIVAL_SHARE = 0.5
# Anchor points farther from their model's nearest Gaussian than this share of its median radius
# are not on it (gsa.align.photo.on_model); anchors of which fewer than MIN_ON_MODEL_SHARE are
# on it belong to another model.
ON_MODEL = 0.05
MIN_ON_MODEL_SHARE = 0.3


@dataclass
class PhotoMatch:
    transform: Sim3 | None
    accepted: bool
    reason: str
    matches: int = 0  # point pairs the descriptors proposed
    inliers: int = 0
    residual_pct: float | None = None  # the inliers' median residual, % of the target's radius

    @property
    def confidence(self) -> float:
        """0 when refused; from 0.5 at the acceptance limits to 1 with half the matches and 100
        point pairs agreeing."""
        if not self.accepted or not self.matches:
            return 0.0
        share = min(1.0, (self.inliers / self.matches - MIN_INLIER_SHARE) / (0.5 - MIN_INLIER_SHARE))
        count = min(1.0, (self.inliers - MIN_INLIERS) / (100 - MIN_INLIERS))
        return 0.5 + 0.25 * max(share, 0.0) + 0.25 * max(count, 0.0)

    def to_dict(self) -> dict:
        return {
            "accepted": self.accepted,
            "confidence": self.confidence,
            "reason": self.reason,
            "matches": self.matches,
            "inliers": self.inliers,
            "inlier_share": self.inliers / self.matches if self.matches else 0.0,
            "residual_pct": self.residual_pct,
        }


def _capped(anchors: PhotoAnchors, limit: int, seed: int) -> PhotoAnchors:
    if len(anchors) <= limit:
        return anchors
    _, rows = np.unique(anchors.point_index, return_index=True)  # one view per point: all points stay
    if len(rows) > limit:
        rows = np.random.default_rng(seed).choice(rows, limit, replace=False)
    rows = np.sort(rows)
    return PhotoAnchors(anchors.points, anchors.descriptors[rows], anchors.point_index[rows])


def matched_pairs(
    src: PhotoAnchors, dst: PhotoAnchors, ratio: float = RATIO, limit: int = MAX_DESCRIPTORS, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """(pairs (M, 2) of source and target point rows, votes (M,)): one vote per descriptor match."""
    import cv2  # lazy: align() imports this module for every pair

    src, dst = _capped(src, limit, seed), _capped(dst, limit, seed + 1)
    if len(src) == 0 or len(dst) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    # A target point has up to MAX_PER_POINT descriptors: the best one of another point is
    # among the k nearest.
    k = min(len(dst), int(np.bincount(dst.point_index).max()) + 1)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(
        src.descriptors.astype(np.float32), dst.descriptors.astype(np.float32), k=k
    )
    pairs = []
    for query in knn:
        if not query:
            continue
        best = query[0]
        best_point = dst.point_index[best.trainIdx]
        other = next((m for m in query[1:] if dst.point_index[m.trainIdx] != best_point), None)
        if other is None or best.distance < ratio * other.distance:
            pairs.append((src.point_index[best.queryIdx], best_point))
    if not pairs:
        return np.zeros((0, 2), np.int64), np.zeros(0)
    unique, votes = np.unique(np.asarray(pairs, np.int64), axis=0, return_counts=True)
    return unique, votes.astype(np.float64)


def _ransac(a: np.ndarray, b: np.ndarray, votes: np.ndarray, tol: float, rng) -> Sim3 | None:
    """The 3-pair similarity most votes agree with (within tol), refitted on its inliers."""
    best_support, best = 0.0, None
    for _ in range(RANSAC_SAMPLES):
        pick = rng.choice(len(a), 3, replace=False)
        try:
            pose = solve_sim3(a[pick], b[pick])
        except DegenerateCorrespondencesError:
            continue
        support = votes[np.linalg.norm(pose.apply(a) - b, axis=1) < tol].sum()
        if support > best_support:
            best_support, best = support, pose
    if best is None:
        return None
    inside = np.zeros(len(a), bool)
    for _ in range(5):  # refit on the inliers until they settle
        inside_now = np.linalg.norm(best.apply(a) - b, axis=1) < tol
        if inside_now.sum() < 3 or (inside_now == inside).all():
            break
        inside = inside_now
        try:
            best = solve_sim3(a[inside], b[inside], votes[inside])
        except DegenerateCorrespondencesError:
            break
    return best


def register(src: PhotoAnchors, dst: PhotoAnchors, seed: int = 0) -> PhotoMatch:
    """The Sim(3) source -> target that the photos' matched texture supports, or a refusal."""
    pairs, votes = matched_pairs(src, dst, seed=seed)
    if len(pairs) < MIN_INLIERS:
        return PhotoMatch(None, False, f"{len(pairs)} point pairs matched (need {MIN_INLIERS})", len(pairs))
    a = src.points[pairs[:, 0]]
    b = dst.points[pairs[:, 1]]
    centre = np.median(b, axis=0)
    radius = float(np.median(np.linalg.norm(b - centre, axis=1)))
    if not radius > 0:
        return PhotoMatch(None, False, "the target's matched points coincide", len(pairs))
    tol = INLIER_RADIUS * radius
    rng = np.random.default_rng(seed)
    best = _ransac(a, b, votes, tol, rng)
    if best is None:
        return PhotoMatch(None, False, "every sample of matched points was degenerate", len(pairs))
    residual = np.linalg.norm(best.apply(a) - b, axis=1)
    inside = residual < tol
    n = int(inside.sum())
    row = PhotoMatch(best, False, "", len(pairs), n, float(100 * np.median(residual[inside]) / radius) if n else None)
    spread = np.linalg.svd(b[inside] - b[inside].mean(axis=0), compute_uv=False) if n >= 3 else np.zeros(3)
    if n < MIN_INLIERS or n < MIN_INLIER_SHARE * len(pairs):
        row.reason = (
            f"{n} of {len(pairs)} matched point pairs agree on one pose (need {MIN_INLIERS} and {MIN_INLIER_SHARE:.0%})"
        )
        return row
    if spread[1] < MIN_SPREAD * spread[0]:
        row.reason = "the agreeing points lie on a line: the rotation about it is not fixed"
        return row
    # Repeated texture (a pattern printed twice, windows along a facade) can make a second pose
    # that many pairs agree with: the photos then do not decide, and the geometry answers.
    rest = ~inside
    rival = _ransac(a[rest], b[rest], votes[rest], tol, rng) if rest.sum() >= MIN_INLIERS else None
    m = int((np.linalg.norm(rival.apply(a[rest]) - b[rest], axis=1) < tol).sum()) if rival is not None else 0
    if m >= MIN_INLIERS and m >= RIVAL_SHARE * n:
        row.reason = (
            f"two poses agree with the photos' matched points ({n} and {m} of {len(pairs)} pairs; "
            f"{np.degrees(rotation_angle(best.rotation.T @ rival.rotation)):.0f}° apart): repeated texture"
        )
        return row
    row.accepted = True
    row.reason = f"{n} of {len(pairs)} matched point pairs agree"
    return row


def photo_anchors(model) -> PhotoAnchors | None:
    """The model's photo anchors that lie on its own Gaussians, or None.

    SfM also triangulates what the model leaves out (masked background, the room around an
    object): two different objects photographed in one place share that background, and
    matching it would place one where it stood instead of onto the other. So only points within
    ON_MODEL of the model's median radius from one of its Gaussians take part. Where fewer than
    MIN_ON_MODEL_SHARE of the points do, the anchors do not belong to this model (edited,
    transformed or swapped after its reconstruction) and none are used."""
    anchors = model.metadata.get("photo_anchors")
    if not isinstance(anchors, PhotoAnchors) or len(anchors) == 0 or len(model) == 0:
        return None
    on = on_model(anchors.points, model.means)
    if on.sum() < MIN_INLIERS or on.mean() < MIN_ON_MODEL_SHARE:
        return None
    return anchors.subset(on)


def on_model(points: np.ndarray, means: np.ndarray) -> np.ndarray:
    """Which points lie within ON_MODEL × the model's median radius of one of its Gaussians
    (reconstructions' SfM points: median 1.5 %, 90 % within 3.4 %)."""
    from scipy.spatial import cKDTree

    means = np.asarray(means, np.float64)
    if len(means) > 200_000:  # the radius and the nearest Gaussian need no more
        means = means[np.random.default_rng(0).choice(len(means), 200_000, replace=False)]
    radius = float(np.median(np.linalg.norm(means - np.median(means, axis=0), axis=1)))
    if not radius > 0:
        return np.zeros(len(points), bool)
    dist, _ = cKDTree(means).query(points, distance_upper_bound=ON_MODEL * radius)
    return np.isfinite(dist)
