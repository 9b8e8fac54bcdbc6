"""Which way up two spinning models are (a vase, a bottle, a mug without its handle): their
open ends. A model that turns freely about an axis has a frame that is any turn about it, so
the relabelling choice cannot tell its ends apart, and across instances neither the mass
profile nor the lifted features did (docs/benchmarks.md, "Views placed in the frames" and the
spin axes after it): upside-down vases were the misses left. One cue does not depend on
proportions: a container's mouth is an open ring where its foot is a filled disk, and two
instances' open ends correspond. Read only where both ends of both models say so plainly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsa import manhattan
from gsa.align import frame_snap, robust
from gsa.geometry import axis_rotation
from gsa.sim3 import Sim3


@dataclass(frozen=True)
class OpenEndCriteria:
    # An end is the slab within this share of the model's length along its axis from the end.
    slab: float = 0.03
    # The share of an end slab's points within half the slab's radius: a filled disk puts about
    # a fifth there (a quarter of its area, diluted by the wall's ring), an open ring none. An
    # end reads open at most `open_share`, closed at least `closed_share`; a model says which
    # end is open only when one reads open and the other closed.
    open_share: float = 0.05
    closed_share: float = 0.1
    # Fewer points than this in an end slab say nothing.
    min_points: int = 30


def axis_of(rotation: np.ndarray) -> np.ndarray:
    """The unit axis of a rotation (not a half turn): from its skew-symmetric part."""
    r = np.asarray(rotation, np.float64)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return axis / np.linalg.norm(axis)


def end_fill(points: np.ndarray, axis: np.ndarray, criteria: OpenEndCriteria | None = None) -> list[float | None]:
    """The share of each end slab's points (the +axis end, then the -axis end) within half the
    slab's radius from the axis through the points' centroid; None where a slab is too sparse."""
    k = criteria or OpenEndCriteria()
    centred = np.asarray(points, np.float64) - np.mean(points, axis=0)
    along = centred @ axis
    radial = np.linalg.norm(centred - np.outer(along, axis), axis=1)
    lo, hi = np.percentile(along, [0.5, 99.5])  # stray points beyond the ends say nothing
    depth = k.slab * (hi - lo)
    out: list[float | None] = []
    for in_slab in (along >= hi - depth, along <= lo + depth):
        r = radial[in_slab]
        if len(r) < k.min_points:
            out.append(None)
            continue
        out.append(float(np.mean(r < 0.5 * np.percentile(r, 95))))
    return out


def open_direction(points: np.ndarray, axis: np.ndarray, criteria: OpenEndCriteria | None = None) -> np.ndarray | None:
    """The unit vector along `axis` that points to the model's open end, where one end reads
    open and the other closed; None where the ends do not say (both open, both filled, sparse)."""
    k = criteria or OpenEndCriteria()
    plus, minus = end_fill(points, axis, k)
    if plus is None or minus is None:
        return None
    if plus <= k.open_share and minus >= k.closed_share:
        return axis.copy()
    if minus <= k.open_share and plus >= k.closed_share:
        return -axis
    return None


def turned_end_for_end(pose: Sim3, axis: np.ndarray, centre: np.ndarray) -> Sim3:
    """`pose` with the source first turned by half a turn about an axis perpendicular to its
    spin `axis` through the source point `centre` (its ends swapped, its place kept)."""
    perpendicular = np.cross(axis, np.eye(3)[int(np.argmin(np.abs(axis)))])
    flip = axis_rotation(perpendicular / np.linalg.norm(perpendicular), np.pi)
    centre = np.asarray(centre, np.float64)
    return pose @ Sim3(1.0, flip, centre - flip @ centre)


def turn_open_ends(pair, best, transform: Sim3, metrics: dict) -> tuple[Sim3, dict]:
    """A doubtful answer between two whole models that both spin freely, turned end for end
    where it maps the source's open end onto the target's closed one (open_direction, read on
    each model's surface without its floaters); the pose replaced becomes the first
    alternative. Where either model does not spin, or its ends do not say which is open, the
    answer is kept. `pair` is the pipeline's _Pair. The answer stays doubtful."""
    source_turns, target_turns = pair.source_symmetries, pair.target_symmetries
    if not (source_turns and target_turns):
        return transform, metrics
    src, dst = pair.anchors()
    source_points, target_points = pair.src_pts[src.kept], pair.dst_pts[dst.kept]
    source_axis = axis_of(source_turns[0])
    k = pair.criteria.open_ends
    source_open = open_direction(source_points, source_axis, k)
    target_open = open_direction(target_points, axis_of(target_turns[0]), k)
    report: dict = {
        "source_open": None if source_open is None else source_open.round(4).tolist(),
        "target_open": None if target_open is None else target_open.round(4).tolist(),
        "turned": False,
    }
    if source_open is None or target_open is None:
        return transform, metrics | {"open_ends": report}
    report["agreement"] = round(float((transform.rotation @ source_open) @ target_open), 4)
    if report["agreement"] >= 0.0:
        return transform, metrics | {"open_ends": report}
    turned = turned_end_for_end(transform, source_axis, source_points.mean(axis=0))
    turned = manhattan.fit_shift(turned, src.points, dst.points, pair.criteria.pose.truncation * dst.radius)
    others = [
        alt
        for alt in metrics.get("alternatives") or []
        if robust.rotation_offset_deg(Sim3.from_matrix(np.asarray(alt["transform"], np.float64)), turned)
        > frame_snap.FRAME_SNAP_SAME_DEG
    ]
    return turned, metrics | pair.judge.quality(turned, best) | {
        "alternatives": [frame_snap.replaced_pose(transform, metrics, "before the open-end turn")] + others,
        "open_ends": report | {"turned": True},
    }
