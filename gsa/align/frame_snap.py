"""The frame snap (docs/how-it-works.md, "Frame snap"): a doubtful answer between other
instances, and its alternatives, turned onto the nearest relabelling of the two models'
dominant surface-normal frames (gsa.manhattan). Across instances the refinement drifts 5-37
degrees off the frame both objects are built along, where one of the 24 relabellings is within
5 degrees of the truth on every category-real pair (docs/benchmarks.md, "Dominant-normal
frames"). `pair` is the pipeline's _Pair: its models, anchors and quality metrics.
"""

from __future__ import annotations

import numpy as np

from gsa import manhattan
from gsa.align import guided, robust
from gsa.sim3 import Sim3

# A doubtful pose this near a relabelling of the dominant-normal frames is turned onto it:
# across instances the refinement drifts 5-20 degrees off the frame both are built along
# (docs/benchmarks.md, "Dominant-normal frames"), while a pose farther off meant another one.
FRAME_SNAP_DEG = 20.0
# Alternatives that land this near the chosen pose or an earlier alternative once snapped are that pose.
FRAME_SNAP_SAME_DEG = 2.0


def guided_snap(pair, best, transform: Sim3, metrics: dict, start: dict, symmetries) -> tuple[Sim3, dict]:
    """A doubtful answer refined from a user's pose or picked pairs, between other instances:
    turned onto the frames as a search answer is, where the turned pose is still the answer the
    user pointed at (guided.near_start). A user's up axes are kept as given: no turn then."""
    opts = pair.opts
    if opts.frame_snap == "off" or opts.up_axes is not None or not other_instances(metrics):
        return transform, metrics
    turned, updated = snap_to_frames(pair, best, transform, metrics)
    if turned is transform or not guided.near_start(turned, best.init, opts, dict(start), symmetries=symmetries):
        return transform, metrics
    return turned, updated


def other_instances(metrics: dict) -> bool:
    """Whether the answer's models differ everywhere (robust.refinement's test: the overlap
    estimate keeps nearly every pair yet fewer than half coincide at the sampling): another
    instance or a deformed copy, where the refinement's fit is not exact. Two captures of one
    object coincide where they overlap: their fit stands."""
    fraction, share = metrics.get("overlap_estimate"), metrics.get("coincident_share")
    k = robust.RefineCriteria()
    return fraction is not None and share is not None and fraction >= k.whole_overlap and share < k.coincident_share


def snap_to_frames(pair, best, transform: Sim3, metrics: dict) -> tuple[Sim3, dict]:
    """A doubtful answer and its alternatives turned onto the nearest relabelling of the two
    models' dominant-normal frames (gsa.manhattan) where that turn is at most FRAME_SNAP_DEG;
    the pose as refined becomes the first alternative. The answer stays doubtful: which of
    the relabellings is right is the question the snap does not answer."""
    frames = manhattan.manhattan_frame(pair.source), manhattan.manhattan_frame(pair.target)
    src, dst = pair.anchors()
    report = {"support": [frames[0].support, frames[1].support], "max_deg": FRAME_SNAP_DEG}

    def snap(pose: Sim3) -> tuple[Sim3, float]:
        return manhattan.snapped(pose, *frames, src.center)

    kept: list[Sim3] = []
    alternatives = []
    chosen, gap = snap(transform)
    snapping = 1e-6 < gap <= FRAME_SNAP_DEG
    if snapping:
        chosen = manhattan.fit_shift(chosen, src.points, dst.points, robust.PoseCriteria().truncation * dst.radius)
        kept.append(chosen)
        alternatives.append(
            {
                "origin": "before the frame snap",
                "score": metrics.get("score"),
                "geometry": metrics.get("overlap_score"),
                "semantic_score": metrics.get("semantic_score"),
                "transform": transform.matrix().tolist(),
            }
        )
    else:
        kept.append(transform)
    for alt in metrics.get("alternatives") or []:
        pose = Sim3.from_matrix(np.asarray(alt["transform"], np.float64))
        turned, alt_gap = snap(pose)
        if 1e-6 < alt_gap <= FRAME_SNAP_DEG:
            pose = manhattan.fit_shift(turned, src.points, dst.points, robust.PoseCriteria().truncation * dst.radius)
            alt = alt | {"transform": pose.matrix().tolist(), "snapped_deg": alt_gap}
        if all(robust.rotation_offset_deg(pose, k) > FRAME_SNAP_SAME_DEG for k in kept):
            kept.append(pose)
            alternatives.append(alt | {"rotation_offset_deg": robust.rotation_offset_deg(pose, kept[0])})
    if not snapping:
        return transform, metrics | {"frame_snap": report | {"used": False, "deg": gap}, "alternatives": alternatives}
    updated = metrics | pair.quality(chosen, best) | {"alternatives": alternatives}
    return chosen, updated | {"frame_snap": report | {"used": True, "deg": gap}}
