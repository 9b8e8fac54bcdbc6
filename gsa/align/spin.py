"""The turn about a nearly turn-symmetric object's axis, settled by the parts that break the
symmetry (a mug's handle, a jug's spout, a lamp's arm).

A mug's body fits any turn about its axis, so the geometric fit of two mugs decides the turn
on the few points of the handle and drifts 8-20 deg along the body's valley, even from a
person's start or clicks (held-out mugs, docs/benchmarks.md "guided"). Here each model's
surface is split into the part that maps onto itself when turned about the axis (the body)
and the part that does not (the handle); the turn about the target's axis that lays the
source's breaking part onto the target's is searched over the full circle and taken where it
stands out. No category rule: a model with no such part (a bottle), or parts that overlap
alike at every turn, leaves the pose as it was.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gsa.geometry import axis_rotation
from gsa.sim3 import Sim3


@dataclass(frozen=True)
class SpinCriteria:
    """The tunables of the spin settle."""

    sample_size: int = 3000  # surface points per model the symmetry is measured on
    # A model nearly spins about an axis when, turned about it by each of test_turns_deg, half
    # of its points still lie within body_spacings sample spacings of its surface ...
    test_turns_deg: tuple[float, ...] = (45.0, 90.0, 135.0, 180.0)
    body_spacings: float = 2.0
    # ... and a point belongs to the breaking part when, turned by most of breaking_turns_deg,
    # it lands farther than breaking_spacings spacings from the surface.
    breaking_turns_deg: tuple[float, ...] = (60.0, 120.0, 180.0, 240.0, 300.0)
    breaking_spacings: float = 3.0
    # The breaking part must be this share of each surface at least (else it is noise) and at most
    # (else the model does not nearly spin).
    breaking_min_share: float = 0.02
    breaking_max_share: float = 0.35
    step_deg: float = 2.0  # the turns tried about the axis
    axis_agree_deg: float = 10.0  # the answer maps the source's axis within this of the target's
    # Breaking points of one model count as laid onto the other's by how close they come, down to
    # nothing at this share of the breaking part's distance from the axis (two instances'
    # handles differ in shape).
    match_share: float = 0.25
    # The best turn is taken where its overlap of the breaking parts is at least min_overlap and
    # lead_ratio times the median over all turns (a handle lies in one place; a pattern of
    # ribs overlaps alike at every turn).
    min_overlap: float = 0.2
    lead_ratio: float = 2.0


_DEFAULT = SpinCriteria()


@dataclass(frozen=True)
class _Spinner:
    axis: np.ndarray  # unit, model coordinates
    pivot: np.ndarray  # a point on the axis: the body's centroid
    breaking: np.ndarray  # (B, 3) the points off the turn symmetry


def _sample(points: np.ndarray, size: int) -> np.ndarray:
    if len(points) <= size:
        return points
    return points[np.random.default_rng(0).choice(len(points), size, replace=False)]


def _axis_line(points: np.ndarray, normals: np.ndarray, rounds: int = 3) -> tuple[np.ndarray, np.ndarray] | None:
    """The line every surface normal of a surface of revolution meets (its axis): (unit
    direction, a point on it), fitted in least squares on the normal lines, the worst-fitting
    30 % (the handle) left out and the fit taken again; None where the fit is degenerate
    (a plane, a sphere: no single axis)."""
    centre = points.mean(0)
    scale = float(np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1)))) or 1.0
    p = (points - centre) / scale
    keep = np.ones(len(p), bool)
    for _ in range(rounds):
        # (p - c)·(a × n) = 0  <=>  a·(n × p) - n·m = 0 with the moment m = c × a
        rows = np.hstack([np.cross(normals[keep], p[keep]), -normals[keep]])
        _, sv, vt = np.linalg.svd(rows, full_matrices=False)
        a, m = vt[-1, :3], vt[-1, 3:]
        norm = float(np.linalg.norm(a))
        if norm < 1e-6:
            return None
        a, m = a / norm, m / norm
        residual = np.abs(np.cross(normals, p) @ a - normals @ m)
        keep = residual <= np.quantile(residual, 0.7)
    # one clear solution: the next one fits the normals far worse (not a sphere, not a plane)
    if sv[-1] > 0.25 * sv[-2]:
        return None
    return a, centre + scale * np.cross(a, m)


def _spinner(model, k: SpinCriteria) -> _Spinner | None:
    """The axis `model`'s surface nearly spins about and the points that break the symmetry;
    None where it does not nearly spin."""
    # a few times the sample, of the opaque Gaussians; then those flat enough to have a normal
    rows = _sample(np.flatnonzero(model.opacities > 0.5), 4 * k.sample_size)
    normals, flatness = model.surface_normals(rows)
    flat = flatness > 0.5
    if flat.sum() < 50:
        return None
    keep = _sample(np.flatnonzero(flat), k.sample_size)
    sample, normals = np.asarray(model.means[rows[keep]], np.float64), normals[keep]
    line = _axis_line(sample, normals)
    if line is None:
        return None
    axis, pivot = line
    tree = cKDTree(sample)
    spacing = float(np.mean(tree.query(sample, k=2)[0][:, 1]))

    def distances(deg: float) -> np.ndarray:
        turn = axis_rotation(axis, np.radians(deg))
        return tree.query((sample - pivot) @ turn.T + pivot)[0]

    if not all(np.median(distances(d)) <= k.body_spacings * spacing for d in k.test_turns_deg):
        return None
    off = np.median(np.stack([distances(d) for d in k.breaking_turns_deg]), axis=0)
    breaking = off > k.breaking_spacings * spacing
    if not k.breaking_min_share <= breaking.mean() <= k.breaking_max_share:
        return None
    return _Spinner(axis, pivot, sample[breaking])


def settle_spin(source, target, pose: Sim3, criteria: SpinCriteria | None = None) -> tuple[Sim3, dict] | None:
    """`pose` (source -> target, its tilt right) turned about the target's axis so the two
    models' symmetry-breaking parts coincide, with a report; None where either model does not
    nearly spin or no turn stands out."""
    k = criteria or _DEFAULT
    src = _spinner(source, k)
    if src is None:
        return None
    mapped_axis = pose.rotation @ src.axis
    dst = _spinner(target, k)
    # the answer's tilt is taken as right: the target's axis must be the source's, mapped
    if dst is None or abs(float(dst.axis @ mapped_axis)) < np.cos(np.radians(k.axis_agree_deg)):
        return None
    axis = dst.axis if float(dst.axis @ mapped_axis) >= 0 else -dst.axis
    pivot = dst.pivot
    # the source's axis laid onto the target's first (the bodies coaxial), then turned about it
    gap = dst.pivot - pose.apply(src.pivot[None])[0]
    pose = Sim3(pose.scale, pose.rotation, pose.translation + gap - (gap @ axis) * axis)
    moved = pose.apply(src.breaking)
    reach = k.match_share * float(np.sqrt(np.mean(np.sum((dst.breaking - dst.pivot) ** 2, axis=1))))
    target_tree = cKDTree(dst.breaking)

    def overlap(deg: float) -> float:
        turn = axis_rotation(axis, np.radians(deg))
        placed = (moved - pivot) @ turn.T + pivot
        forward = np.clip(1.0 - target_tree.query(placed)[0] / reach, 0.0, 1.0)
        backward = np.clip(1.0 - cKDTree(placed).query(dst.breaking)[0] / reach, 0.0, 1.0)
        return 0.5 * float(forward.mean() + backward.mean())

    turns = np.arange(0.0, 360.0, k.step_deg)
    overlaps = np.array([overlap(deg) for deg in turns])
    best = int(np.argmax(overlaps))
    # then to a tenth of the step about the best
    fine = turns[best] + np.linspace(-k.step_deg, k.step_deg, 21)
    fine_overlaps = [overlap(deg) for deg in fine]
    chosen = float(fine[int(np.argmax(fine_overlaps))]) % 360.0
    report = {
        "turn_deg": chosen if chosen <= 180 else chosen - 360,
        "overlap": round(float(max(fine_overlaps)), 4),
        "at_answer": round(float(overlaps[0]), 4),
        "median": round(float(np.median(overlaps)), 4),
        "breaking_points": [len(src.breaking), len(dst.breaking)],
    }
    if overlaps[best] < k.min_overlap or overlaps[best] < k.lead_ratio * float(np.median(overlaps)):
        return None
    turn = axis_rotation(axis, np.radians(chosen))
    turned = Sim3(1.0, turn, pivot - turn @ pivot).compose(pose)
    return turned, report
